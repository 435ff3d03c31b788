#!/usr/bin/env bash
# Runs the README's demo, shortened (two robots), on the DDS domain CTest gave this test, and
# checks what it leaves behind: a PASS verdict, the merged map and its picture.
set -euo pipefail
src=$1 bin=$2
domain=${CTEST_RESOURCE_GROUP_0_DOMAINS:-id:$((RANDOM % 90 + 5)),slots:1}
domain=${domain#id:}; domain=${domain%%,*}
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
cd "$src"
MAPMERGE_DEMO_SKIP_BUILD=1 MAPMERGE_BUILD_DIR="$bin" MAPMERGE_DOMAIN="$domain" MAPMERGE_DEMO_OUT="$out/demo" \
  MAPMERGE_DEMO_ROBOTS=2 MAPMERGE_DEMO_SEED=${MAPMERGE_DEMO_SEED:-11} MAPMERGE_DEMO_TIMEOUT=180 \
  scripts/demo | tee "$out/demo.txt"
grep -q '^PASS: 2 of 2 robots' "$out/demo.txt"
test -s "$out/demo/global.bt"
test -s "$out/demo/global.png"
test -s "$out/demo/global.prov"  # the picture is coloured by robot from the server's provenance
