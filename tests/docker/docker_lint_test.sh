#!/usr/bin/env bash
# Lints docker/ without a Docker daemon (there is none on the CI machine):
#   compose     docker/compose.yaml passes docker-compose's own schema check (Debian's docker-compose)
#   dockerfile  the image's build stage takes exactly CI's steps (scripts/setup, scripts/build)
#               and the runtime stage starts the installed programs
#   install     `cmake --install` of this build (what the build stage copies into the runtime
#               image) holds the programs, the sample maps the compose file uses, and
#               docker/runtime-packages names an installed Debian package for every library
#               the programs load
set -euo pipefail
what=$1 src=$2 bin=$3
dockerfile=$src/docker/Dockerfile compose=$src/docker/compose.yaml
fail() { echo "FAIL: $*" >&2; exit 1; }

case $what in
compose)
  command -v docker-compose >/dev/null || fail "docker-compose is missing (scripts/setup installs it)"
  docker-compose -f "$compose" config -q
  config=$(docker-compose -f "$compose" config)
  # Every program the compose file starts is one the image installs (cmake --install of
  # this build is what the build stage copies into the runtime image).
  prefix=$(mktemp -d)
  trap 'rm -rf "$prefix"' EXIT
  cmake --install "$bin" --prefix "$prefix" >/dev/null
  progs=$(echo "$config" | awk '/entrypoint:/{getline; print $2}' | sort -u)
  [ -n "$progs" ] || fail "found no entrypoint in the compose file"
  for prog in $progs mapmerge-server; do
    [ -x "$prefix/bin/$prog" ] || fail "compose starts '$prog', which the image does not install"
  done
  # The fleet network reaches nothing outside; the server runs with a memory limit (README).
  grep -q 'internal: true' <<<"$config" || fail "fleet network is not internal"
  grep -q 'mem_limit' <<<"$config" || fail "server has no memory limit"
  # The scenario service's command works on the installed tree (paths mapped into it).
  scenario=$(awk '/^  scenario:/{f=1} f&&/entrypoint:/{e=1; next} e&&/^    - /{print $2; next} e{exit}' <<<"$config" |
             sed -e "s|^/opt/mapmerge/|$prefix/|" -e "s|^/scenario\$|$prefix/scenario|" -e "s|^'\\(.*\\)'\$|\\1|" | tr '\n' ' ')
  mkdir -p "$prefix/scenario"
  (cd "$prefix/bin" && PATH=$prefix/bin:$PATH $scenario) >/dev/null || fail "the scenario service fails: $scenario"
  for r in r1 r2; do [ -s "$prefix/scenario/$r.bt" ] || fail "the scenario service wrote no $r.bt"; done
  ;;
dockerfile)
  # One build stage from Debian 12 running the project's own scripts, then a slim runtime stage.
  grep -q '^FROM debian:12 AS build' "$dockerfile" || fail "build stage is not Debian 12"
  grep -q '^FROM debian:12-slim AS runtime' "$dockerfile" || fail "runtime stage is not Debian 12 slim"
  grep -q '^RUN scripts/setup' "$dockerfile" || fail "build stage does not install with scripts/setup"
  grep -q 'scripts/build' "$dockerfile" || fail "build stage does not build with scripts/build"
  if grep -n 'apt-get install' "$dockerfile" | grep -v 'runtime-packages' | grep -q .; then
    fail "the Dockerfile installs packages by hand instead of through scripts/setup or runtime-packages"
  fi
  grep -q 'docker/runtime-packages' "$dockerfile" || fail "runtime packages are not derived from the binaries"
  grep -q '^USER mapmerge' "$dockerfile" || fail "the runtime image runs as root"
  grep -q '^ENTRYPOINT \["mapmerge-server"\]' "$dockerfile" || fail "the image does not start the server"
  ;;
install)
  prefix=$(mktemp -d)
  trap 'rm -rf "$prefix"' EXIT
  cmake --install "$bin" --prefix "$prefix" >/dev/null
  for prog in mapmerge mapmerge-server mapmerge-robot mapmerge-listen; do
    [ -x "$prefix/bin/$prog" ] || fail "$prog is not installed"
    "$prefix/bin/$prog" --help >/dev/null || fail "$prog --help fails"
  done
  map=$(docker-compose -f "$compose" config 2>/dev/null | grep -o '/opt/mapmerge/share/mapmerge/data/[^ ]*\.bt' | head -1 || true)
  map=${map:-/opt/mapmerge/share/mapmerge/data/geb079.bt}
  [ -s "$prefix/${map#/opt/mapmerge/}" ] || fail "the compose file's map ${map} is not installed"
  packages=$("$src/docker/runtime-packages" "$prefix"/bin/*)
  [ -n "$packages" ] || fail "runtime-packages found no package"
  for p in $packages; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" ||
      fail "runtime-packages names '$p', which is not an installed Debian package"
  done
  # Every shared library a program loads comes from one of those packages (else the runtime
  # image would miss it).
  missing=$(ldd "$prefix"/bin/* | awk '/=> \//{print $3}' | grep -v "^$prefix/" | sort -u | while read -r lib; do
    owner=$(dpkg -S "$(readlink -f "$lib")" 2>/dev/null || dpkg -S "$lib" 2>/dev/null || true)
    [ -n "$owner" ] || echo "$lib"
  done)
  [ -z "$missing" ] || fail "libraries no Debian package provides: $missing"
  echo "runtime packages: $(echo $packages | wc -w)"
  ;;
*) fail "unknown check $what" ;;
esac
echo "ok: $what"
