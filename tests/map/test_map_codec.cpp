// Wire codec: round trips on real maps, and every hostile case rejected with its own reason.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <random>
#include <sstream>
#include <string>

#include <zstd.h>

#include "map_test_util.hpp"
#include "mapmerge/map/bounds.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/held_map.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"

namespace mapmerge {
namespace {

using test::as_bytes;
using test::as_string;
using test::body_offset;
using test::file_bytes;

const char* const kMaps[] = {"fr_079.bt", "geb079.bt", "fr_078_tidyup.bt"};

DecodeResult decode_bt(const std::vector<std::uint8_t>& bytes, const DecodeLimits& limits = {}) {
  return decode_map(bytes, Encoding::kOctomapBt, limits);
}

/// Replaces the first occurrence of `from` in the header of `bytes` by `to`.
std::vector<std::uint8_t> edit_header(const std::vector<std::uint8_t>& bytes,
                                      const std::string& from, const std::string& to) {
  std::string text = as_string(bytes);
  const std::size_t pos = text.find(from);
  EXPECT_NE(pos, std::string::npos) << from;
  EXPECT_LT(pos, body_offset(bytes));
  text.replace(pos, from.size(), to);
  return as_bytes(text);
}

std::string size_line(const std::vector<std::uint8_t>& bytes) {
  const std::string text = as_string(bytes);
  const std::size_t pos = text.find("\nsize ") + 1;
  return text.substr(pos, text.find('\n', pos) - pos);
}

// --- round trips -------------------------------------------------------------------------------

class RealMap : public ::testing::TestWithParam<const char*> {};

TEST_P(RealMap, BinaryRoundTripIsByteIdentical) {
  const auto bytes = file_bytes(GetParam());
  ASSERT_GT(bytes.size(), 1000U);
  const DecodeResult decoded = decode_bt(bytes);
  ASSERT_TRUE(decoded.ok()) << decoded.reason;
  EXPECT_FALSE(decoded.empty);
  EXPECT_EQ(size_line(bytes), "size " + std::to_string(decoded.num_nodes));
  EXPECT_EQ(encode_map(*decoded.tree, Encoding::kOctomapBt), bytes);
}

TEST_P(RealMap, CheckedMapBuildsItsTreeOnlyWhenAskedAndItIsTheDecodedTree) {
  const auto bytes = file_bytes(GetParam());
  const CheckedMap checked = check_map(bytes, "octomap-bt", DecodeLimits{});
  ASSERT_TRUE(checked.ok() && checked.map) << checked.reason;
  const DecodeResult decoded = decode_bt(bytes);
  EXPECT_FALSE(checked.map->has_tree());
  EXPECT_EQ(checked.map->num_nodes(), decoded.num_nodes);
  EXPECT_EQ(checked.map->resolution(), decoded.tree->getResolution());
  ASSERT_TRUE(checked.map->binary_body() && decoded.binary_body);
  EXPECT_TRUE(*checked.map->binary_body() == *decoded.binary_body);
  const auto tree = checked.map->tree();
  EXPECT_TRUE(checked.map->has_tree());
  EXPECT_EQ(checked.map->tree(), tree);  // built once
  EXPECT_EQ(encode_map(*tree, Encoding::kOctomapBt), bytes);
  // A full-format payload is kept as its full body the same way, its tree built when asked.
  const auto full = encode_map(*decoded.tree, Encoding::kOctomapOt);
  const CheckedMap ot = check_map(full, "octomap-ot", DecodeLimits{});
  ASSERT_TRUE(ot.ok() && ot.map) << ot.reason;
  EXPECT_FALSE(ot.map->has_tree());
  EXPECT_EQ(ot.map->binary_body(), nullptr);
  ASSERT_NE(ot.map->full_body(), nullptr);
  EXPECT_EQ(ot.map->num_nodes(), decoded.num_nodes);
  EXPECT_EQ(encode_map(*ot.map->tree(), Encoding::kOctomapOt), full);
  EXPECT_TRUE(ot.map->has_tree());
  EXPECT_TRUE(ot.map->release_tree());  // the body stays: the tree can be let go of
  EXPECT_FALSE(ot.map->has_tree());
}

TEST_P(RealMap, DecodedTreeEqualsOctomapsOwnReaderNodeForNode) {
  const auto bytes = file_bytes(GetParam());
  const DecodeResult decoded = decode_bt(bytes);
  ASSERT_TRUE(decoded.ok()) << decoded.reason;
  octomap::OcTree reference(decoded.tree->getResolution());
  std::istringstream in(as_string(bytes).substr(body_offset(bytes)));
  reference.readBinaryData(in);
  ASSERT_EQ(decoded.tree->size(), reference.size());
  ASSERT_EQ(decoded.tree->size(), reference.calcNumNodes());
  // Every node, inner ones included, in the same order with the same key, depth and value.
  auto a = decoded.tree->begin_tree(), b = reference.begin_tree();
  std::size_t nodes = 0;
  for (; a != decoded.tree->end_tree() && b != reference.end_tree(); ++a, ++b, ++nodes) {
    ASSERT_EQ(a.getKey(), b.getKey()) << "node " << nodes;
    ASSERT_EQ(a.getDepth(), b.getDepth()) << "node " << nodes;
    ASSERT_EQ(a.isLeaf(), b.isLeaf()) << "node " << nodes;
    ASSERT_EQ(a->getLogOdds(), b->getLogOdds()) << "node " << nodes;
  }
  EXPECT_TRUE(a == decoded.tree->end_tree() && b == reference.end_tree());
  EXPECT_EQ(nodes, reference.size());
  auto bounds = [](const octomap::OcTree& t) {
    std::vector<double> v(6);
    t.getMetricMin(v[0], v[1], v[2]);
    t.getMetricMax(v[3], v[4], v[5]);
    return v;
  };
  EXPECT_EQ(bounds(*decoded.tree), bounds(reference));
}

TEST_P(RealMap, DecodedFullFormatTreeEqualsOctomapsOwnReaderNodeForNode) {
  // A `.ot` body keeps every node's log-odds, inner nodes as stored: give the leaves values of
  // their own (not only the two clamping bounds a `.bt` body knows) and keep the inner ones.
  std::unique_ptr<octomap::OcTree> tree = decode_bt(file_bytes(GetParam())).tree;
  ASSERT_TRUE(tree);
  float step = 0.0F;
  for (auto it = tree->begin_leafs(); it != tree->end_leafs(); ++it) {
    it->setLogOdds(it->getLogOdds() * (0.25F + std::fmod(step += 0.37F, 1.0F)));
  }
  const auto full = encode_map(*tree, Encoding::kOctomapOt);
  const DecodeResult decoded = decode_map(full, Encoding::kOctomapOt, DecodeLimits{});
  ASSERT_TRUE(decoded.ok()) << decoded.reason;
  octomap::OcTree reference(tree->getResolution());
  std::istringstream in(as_string(full).substr(body_offset(full)));
  ASSERT_TRUE(reference.readData(in));
  ASSERT_EQ(decoded.tree->size(), reference.size());
  ASSERT_EQ(decoded.tree->size(), reference.calcNumNodes());
  auto a = decoded.tree->begin_tree(), b = reference.begin_tree();
  std::size_t nodes = 0, fractional = 0;
  for (; a != decoded.tree->end_tree() && b != reference.end_tree(); ++a, ++b, ++nodes) {
    ASSERT_EQ(a.getKey(), b.getKey()) << "node " << nodes;
    ASSERT_EQ(a.getDepth(), b.getDepth()) << "node " << nodes;
    ASSERT_EQ(a.isLeaf(), b.isLeaf()) << "node " << nodes;
    ASSERT_EQ(a->getLogOdds(), b->getLogOdds()) << "node " << nodes;
    fractional += a.isLeaf() && a->getLogOdds() != tree->getClampingThresMaxLog() &&
                  a->getLogOdds() != tree->getClampingThresMinLog();
  }
  EXPECT_TRUE(a == decoded.tree->end_tree() && b == reference.end_tree());
  EXPECT_EQ(nodes, reference.size());
  EXPECT_GT(fractional, nodes / 4);  // the values are the file's, not the bounds
  // Written again, the same bytes.
  EXPECT_EQ(encode_map(*decoded.tree, Encoding::kOctomapOt), full);
}

TEST_P(RealMap, ZstdRoundTripIsByteIdenticalAndSmaller) {
  const auto bytes = file_bytes(GetParam());
  const auto tree = decode_bt(bytes).tree;
  ASSERT_TRUE(tree);
  const auto packed = encode_map(*tree, Encoding::kOctomapBtZstd);
  EXPECT_LT(packed.size(), bytes.size());
  const DecodeResult decoded = decode_map(packed, "octomap-bt+zstd", DecodeLimits{});
  ASSERT_TRUE(decoded.ok()) << decoded.reason;
  EXPECT_EQ(encode_map(*decoded.tree, Encoding::kOctomapBt), bytes);
}

TEST_P(RealMap, FullFormatRoundTripIsByteIdentical) {
  const auto tree = decode_bt(file_bytes(GetParam())).tree;
  ASSERT_TRUE(tree);
  const auto full = encode_map(*tree, Encoding::kOctomapOt);
  const DecodeResult decoded = decode_map(full, Encoding::kOctomapOt, DecodeLimits{});
  ASSERT_TRUE(decoded.ok()) << decoded.reason;
  EXPECT_EQ(decoded.num_nodes, tree->size());
  EXPECT_EQ(encode_map(*decoded.tree, Encoding::kOctomapOt), full);
}

TEST_P(RealMap, Ros2MessageBodiesRoundTrip) {
  const auto tree = decode_bt(file_bytes(GetParam())).tree;
  ASSERT_TRUE(tree);
  for (const bool binary : {true, false}) {
    const auto body = encode_tree_body(*tree, binary);
    const DecodeResult decoded =
        decode_tree_body("OcTree", tree->getResolution(), binary, body, DecodeLimits{});
    ASSERT_TRUE(decoded.ok()) << decoded.reason;
    EXPECT_EQ(decoded.num_nodes, tree->size());
    EXPECT_EQ(encode_tree_body(*decoded.tree, binary), body);
  }
}

INSTANTIATE_TEST_SUITE_P(Data, RealMap, ::testing::ValuesIn(kMaps));

TEST(Codec, EncoderWritesExactlyWhatOctomapsOwnWriterWrites) {
  // An unpruned tree with probabilistic values and an odd resolution, grown from a real map.
  const auto real = decode_bt(file_bytes("geb079.bt")).tree;
  ASSERT_TRUE(real);
  octomap::OcTree tree(0.1234567);
  int i = 0;
  for (auto it = real->begin_leafs(), end = real->end_leafs(); it != end && i < 20000; ++it, ++i) {
    tree.updateNode(it.getCoordinate(), i % 3 != 0);
  }
  std::ostringstream file, body;
  tree.writeBinaryConst(file);
  tree.writeBinaryData(body);
  EXPECT_EQ(as_string(encode_map(tree, Encoding::kOctomapBt)), file.str());
  EXPECT_EQ(as_string(encode_tree_body(tree, true)), body.str());
  const DecodeResult back = decode_bt(encode_map(tree, Encoding::kOctomapBt));
  ASSERT_TRUE(back.ok()) << back.reason;
  EXPECT_EQ(back.num_nodes, tree.size());
}

// --- encoding field ----------------------------------------------------------------------------

TEST(Codec, EncodingNamesRoundTrip) {
  for (const Encoding e : {Encoding::kOctomapBt, Encoding::kOctomapBtZstd, Encoding::kOctomapOt}) {
    EXPECT_EQ(parse_encoding(to_string(e)), e);
  }
  EXPECT_FALSE(parse_encoding("OCTOMAP-BT"));
  EXPECT_FALSE(parse_encoding(""));
}

TEST(Codec, UnknownEncodingFieldIsRejected) {
  const DecodeResult r = decode_map(file_bytes("geb079.bt"), "octomap-png", DecodeLimits{});
  EXPECT_EQ(r.error, DecodeError::kUnknownEncoding);
  EXPECT_FALSE(r.tree);
  EXPECT_NE(r.reason.find("octomap-png"), std::string::npos) << r.reason;
}

TEST(Codec, EncodingFieldThatDoesNotMatchTheBytesIsRejected) {
  const auto bytes = file_bytes("geb079.bt");
  const auto tree = decode_bt(bytes).tree;
  ASSERT_TRUE(tree);
  const auto packed = encode_map(*tree, Encoding::kOctomapBtZstd);
  EXPECT_EQ(decode_bt(packed).error, DecodeError::kEncodingMismatch);
  EXPECT_EQ(decode_map(bytes, Encoding::kOctomapBtZstd, {}).error, DecodeError::kEncodingMismatch);
  EXPECT_EQ(decode_map(bytes, Encoding::kOctomapOt, {}).error, DecodeError::kEncodingMismatch);
  const auto full = encode_map(*tree, Encoding::kOctomapOt);
  EXPECT_EQ(decode_bt(full).error, DecodeError::kEncodingMismatch);
}

// --- empty maps --------------------------------------------------------------------------------

TEST(Codec, EmptyMapIsValidButFlagged) {
  const octomap::OcTree empty(0.05);
  for (const Encoding e : {Encoding::kOctomapBt, Encoding::kOctomapBtZstd, Encoding::kOctomapOt}) {
    const DecodeResult r = decode_map(encode_map(empty, e), e, DecodeLimits{});
    ASSERT_TRUE(r.ok()) << to_string(e) << ": " << r.reason;
    EXPECT_TRUE(r.empty);
    EXPECT_EQ(r.num_nodes, 0U);
    EXPECT_DOUBLE_EQ(r.tree->getResolution(), 0.05);
  }
  const DecodeResult body = decode_tree_body("OcTree", 0.05, true, {}, DecodeLimits{});
  ASSERT_TRUE(body.ok()) << body.reason;
  EXPECT_TRUE(body.empty);
}

TEST(Codec, RootWithoutChildrenIsAnEmptyMapNotAnOccupiedWorld) {
  const DecodeResult r = decode_tree_body("OcTree", 0.05, true, {0, 0}, DecodeLimits{});
  ASSERT_TRUE(r.ok()) << r.reason;
  EXPECT_TRUE(r.empty);
  EXPECT_EQ(r.tree->size(), 0U);
}

// --- hostile bytes: truncation, garbage, structure -----------------------------------------------

TEST(Hostile, TruncatedBytesAreRejectedAtEveryCut) {
  const auto bytes = file_bytes("geb079.bt");
  const std::size_t body = body_offset(bytes);
  int rejected = 0;
  for (std::size_t cut = 0; cut < bytes.size(); cut += 997) {
    const std::vector<std::uint8_t> part(bytes.begin(), bytes.begin() + static_cast<long>(cut));
    const DecodeResult r = decode_bt(part);
    ASSERT_FALSE(r.ok()) << "cut at " << cut;
    EXPECT_EQ(r.error, cut <= body ? DecodeError::kBadHeader : DecodeError::kTruncated)
        << "cut at " << cut << ": " << r.reason;
    ++rejected;
  }
  EXPECT_GT(rejected, 200);
}

TEST(Hostile, StreamEndingMidNodeIsRejected) {
  auto bytes = file_bytes("fr_078_tidyup.bt");
  bytes.resize(body_offset(bytes) + 1001);  // odd: half of a two-byte node record
  const DecodeResult r = decode_bt(bytes);
  EXPECT_EQ(r.error, DecodeError::kTruncated);
  EXPECT_NE(r.reason.find("mid-node"), std::string::npos) << r.reason;
}

TEST(Hostile, GarbageAfterValidDataIsRejected) {
  for (const std::size_t extra : {1, 2, 1000}) {
    auto bytes = file_bytes("geb079.bt");
    bytes.insert(bytes.end(), extra, 0x5A);
    const DecodeResult r = decode_bt(bytes);
    EXPECT_EQ(r.error, DecodeError::kTrailingBytes) << r.reason;
    EXPECT_NE(r.reason.find(std::to_string(extra) + " bytes after"), std::string::npos) << r.reason;
  }
}

TEST(Hostile, HeaderClaimingTenToTheTwelveNodesIsRejectedBeforeParsing) {
  const auto bytes = file_bytes("fr_079.bt");
  const auto forged = edit_header(bytes, size_line(bytes), "size 1000000000000");
  const DecodeResult r = decode_bt(forged);
  EXPECT_EQ(r.error, DecodeError::kTooManyNodes) << r.reason;
  const auto overflow = edit_header(bytes, size_line(bytes), "size 99999999999999999999999");
  EXPECT_EQ(decode_bt(overflow).error, DecodeError::kTooManyNodes);
}

TEST(Hostile, HeaderSizeDisagreeingWithBodyIsRejected) {
  const auto bytes = file_bytes("geb079.bt");
  const auto forged = edit_header(bytes, size_line(bytes), "size 12345");
  const DecodeResult r = decode_bt(forged);
  EXPECT_EQ(r.error, DecodeError::kNodeCountMismatch) << r.reason;
}

TEST(Hostile, NodeCapAppliesToTheBodyItself) {
  DecodeLimits limits;
  limits.max_nodes = 100000;
  const auto bytes = file_bytes("geb079.bt");
  const DecodeResult claimed = decode_bt(bytes, limits);
  EXPECT_EQ(claimed.error, DecodeError::kTooManyNodes);
  // The ROS 2 path has no header count: the pre-pass must stop at the cap on its own.
  const std::vector<std::uint8_t> body(bytes.begin() + static_cast<long>(body_offset(bytes)),
                                       bytes.end());
  const DecodeResult counted = decode_tree_body("OcTree", 0.08, true, body, limits);
  EXPECT_EQ(counted.error, DecodeError::kTooManyNodes) << counted.reason;
}

TEST(Hostile, AllOnesBodyThatWouldOverflowTheStackIsRejectedAsTooDeep) {
  // 200 KB of 0xFF: every child an inner node, forever. OctoMap recurses once per byte pair.
  const std::vector<std::uint8_t> ones(200 * 1024, 0xFF);
  const DecodeResult body = decode_tree_body("OcTree", 0.05, true, ones, DecodeLimits{});
  EXPECT_EQ(body.error, DecodeError::kTooDeep) << body.reason;
  auto file = file_bytes("geb079.bt");
  file.resize(body_offset(file));
  file.insert(file.end(), ones.begin(), ones.end());
  EXPECT_EQ(decode_bt(file).error, DecodeError::kTooDeep);
}

TEST(Hostile, HugeOccupiedLeafIsRejected) {
  // Two bytes: the root's first child is one occupied leaf 1.6 km wide (8^15 voxels at 5 cm),
  // which every consumer expanding pruned leaves (to_points, render) would choke on.
  const DecodeResult r = decode_tree_body("OcTree", 0.05, true, {0x02, 0x00}, DecodeLimits{});
  EXPECT_EQ(r.error, DecodeError::kVolumeTooLarge) << r.reason;
  // A huge free leaf is not expanded by readers, but fusing it would touch ~10^10 voxels.
  const DecodeResult free_leaf = decode_tree_body("OcTree", 0.05, true, {0x01, 0x00}, DecodeLimits{});
  EXPECT_EQ(free_leaf.error, DecodeError::kVolumeTooLarge) << free_leaf.reason;
  DecodeLimits generous;
  generous.max_fusion_work = 1e12;
  EXPECT_TRUE(decode_tree_body("OcTree", 0.05, true, {0x01, 0x00}, generous).ok());
  DecodeLimits limits;
  limits.max_occupied_voxels = 100000;
  EXPECT_EQ(decode_bt(file_bytes("geb079.bt"), limits).error, DecodeError::kVolumeTooLarge);
}

TEST(Hostile, InnerNodeWithoutChildrenIsRejected) {
  // Root: child 0 is an inner node (code 3); that node's record says it has no children.
  const DecodeResult r = decode_tree_body("OcTree", 0.05, true, {0x03, 0x00, 0x00, 0x00}, {});
  EXPECT_EQ(r.error, DecodeError::kMalformedTree) << r.reason;
}

TEST(Hostile, FullFormatWithNonFiniteLogOddsIsRejected) {
  const auto tree = decode_bt(file_bytes("geb079.bt")).tree;
  ASSERT_TRUE(tree);
  auto body = encode_tree_body(*tree, false);
  const float nan = std::nanf("");
  std::memcpy(body.data() + 5, &nan, sizeof(nan));  // the root's first child's value
  const DecodeResult r = decode_tree_body("OcTree", 0.08, false, body, DecodeLimits{});
  EXPECT_EQ(r.error, DecodeError::kBadValue) << r.reason;
}

TEST(Hostile, RandomMutationsOfARealMapNeverCrashAndAreAlwaysConsistent) {
  const auto bytes = file_bytes("geb079.bt");
  const std::size_t body = body_offset(bytes);
  std::mt19937 rng(7);
  int accepted = 0;
  for (int round = 0; round < 150; ++round) {
    auto mutated = bytes;
    std::uniform_int_distribution<std::size_t> where(body, bytes.size() - 1);
    for (int k = 0; k < 1 + round % 4; ++k) mutated[where(rng)] = static_cast<std::uint8_t>(rng());
    const DecodeResult r = decode_bt(mutated);
    const CheckedMap c = check_map(mutated, "octomap-bt", DecodeLimits{});  // same verdict, no tree
    EXPECT_EQ(c.error, r.error) << round;
    if (r.ok()) {
      ++accepted;
      EXPECT_EQ(r.tree->size(), r.num_nodes);
      ASSERT_TRUE(c.map);
      EXPECT_EQ(encode_map(*c.map->tree(), Encoding::kOctomapBt), encode_map(*r.tree, Encoding::kOctomapBt));
    } else {
      EXPECT_FALSE(r.reason.empty());
    }
  }
  EXPECT_LT(accepted, 150);  // flipping bits in the structure must be caught most of the time
}

// --- header values -----------------------------------------------------------------------------

TEST(Hostile, BadResolutionsAreRejected) {
  const auto bytes = file_bytes("geb079.bt");
  for (const char* res : {"0", "-0.08", "nan", "NaN", "inf", "-inf", "1e-300", "1e300", "0.0001",
                          "100"}) {
    const DecodeResult r = decode_bt(edit_header(bytes, "res 0.08", std::string("res ") + res));
    EXPECT_EQ(r.error, DecodeError::kBadResolution) << res << ": " << r.reason;
  }
  EXPECT_EQ(decode_bt(edit_header(bytes, "res 0.08", "res 0.08x")).error, DecodeError::kBadHeader);
  EXPECT_EQ(decode_bt(edit_header(bytes, "res 0.08", "res")).error, DecodeError::kBadHeader);
  // The ROS 2 message path carries the resolution as a double.
  const std::vector<std::uint8_t> body(bytes.begin() + static_cast<long>(body_offset(bytes)),
                                       bytes.end());
  for (const double res : {0.0, -1.0, std::nan(""), 1e-300, std::numeric_limits<double>::infinity()}) {
    EXPECT_EQ(decode_tree_body("OcTree", res, true, body, {}).error, DecodeError::kBadResolution);
  }
}

TEST(Hostile, ConfigurableResolutionRange) {
  DecodeLimits limits;
  limits.min_resolution = 0.1;
  EXPECT_EQ(decode_bt(file_bytes("geb079.bt"), limits).error, DecodeError::kBadResolution);
}

TEST(Hostile, UnknownTreeIdIsRejected) {
  const auto bytes = file_bytes("geb079.bt");
  for (const char* id : {"ColorOcTree", "CountingOcTree", "1", "OcTreee"}) {
    const DecodeResult r = decode_bt(edit_header(bytes, "id OcTree", std::string("id ") + id));
    EXPECT_EQ(r.error, DecodeError::kUnknownTreeId) << id << ": " << r.reason;
  }
  EXPECT_EQ(decode_tree_body("ColorOcTree", 0.05, true, {0, 0}, {}).error,
            DecodeError::kUnknownTreeId);
}

TEST(Hostile, MalformedHeadersAreRejected) {
  const auto bytes = file_bytes("geb079.bt");
  EXPECT_EQ(decode_bt(edit_header(bytes, "# Octomap OcTree binary", "# Octomap OcTrie binary")).error,
            DecodeError::kBadHeader);
  EXPECT_EQ(decode_bt(edit_header(bytes, "\ndata\n", "\ndat\n")).error, DecodeError::kBadHeader);
  EXPECT_EQ(decode_bt(edit_header(bytes, "id OcTree\n", "")).error, DecodeError::kBadHeader);
  EXPECT_EQ(decode_bt(edit_header(bytes, "id OcTree", "id OcTree\nid OcTree")).error,
            DecodeError::kBadHeader);
  EXPECT_EQ(decode_bt(as_bytes(std::string(10000, '#'))).error, DecodeError::kBadHeader);
  EXPECT_EQ(decode_bt({}).error, DecodeError::kBadHeader);
}

// --- size limits and compression ---------------------------------------------------------------

TEST(Hostile, PayloadAtTheByteLimitIsRejectedBeforeParsing) {
  DecodeLimits limits;
  limits.max_bytes = 100000;
  const DecodeResult r = decode_bt(file_bytes("geb079.bt"), limits);
  EXPECT_EQ(r.error, DecodeError::kTooLarge) << r.reason;
}

TEST(Hostile, ZstdFrameDeclaringMoreThanTheLimitIsRejectedWithoutInflating) {
  const auto tree = decode_bt(file_bytes("fr_079.bt")).tree;
  ASSERT_TRUE(tree);
  const auto packed = encode_map(*tree, Encoding::kOctomapBtZstd);
  DecodeLimits limits;
  limits.max_bytes = 600000;  // > compressed size (~440 KB), < the 706 KB it declares
  ASSERT_LT(packed.size(), limits.max_bytes);
  const DecodeResult r = decode_map(packed, Encoding::kOctomapBtZstd, limits);
  EXPECT_EQ(r.error, DecodeError::kTooLarge);
  EXPECT_NE(r.reason.find("declares"), std::string::npos) << r.reason;
}

TEST(Hostile, ZstdBombWithoutDeclaredSizeStopsAtTheLimit) {
  // A streamed frame (no content size) of 64 MB of zeros is a few KB on the wire.
  const std::vector<std::uint8_t> zeros(64 << 20, 0);
  std::unique_ptr<ZSTD_CStream, decltype(&ZSTD_freeCStream)> cs(ZSTD_createCStream(),
                                                                  &ZSTD_freeCStream);
  ZSTD_initCStream(cs.get(), 1);
  std::vector<std::uint8_t> packed(ZSTD_compressBound(zeros.size()));
  ZSTD_outBuffer out{packed.data(), packed.size(), 0};
  ZSTD_inBuffer in{zeros.data(), zeros.size(), 0};
  ZSTD_compressStream(cs.get(), &out, &in);
  ZSTD_endStream(cs.get(), &out);
  packed.resize(out.pos);
  ASSERT_EQ(ZSTD_getFrameContentSize(packed.data(), packed.size()), ZSTD_CONTENTSIZE_UNKNOWN);
  DecodeLimits limits;
  limits.max_bytes = 1 << 20;
  const DecodeResult r = decode_map(packed, Encoding::kOctomapBtZstd, limits);
  EXPECT_EQ(r.error, DecodeError::kTooLarge) << r.reason;
}

TEST(Hostile, CorruptCompressedPayloadIsRejected) {
  const auto tree = decode_bt(file_bytes("geb079.bt")).tree;
  ASSERT_TRUE(tree);
  const auto packed = encode_map(*tree, Encoding::kOctomapBtZstd);
  auto flipped = packed;
  flipped[flipped.size() / 2] ^= 0x40;
  EXPECT_EQ(decode_map(flipped, Encoding::kOctomapBtZstd, {}).error,
            DecodeError::kDecompressionFailed);
  auto cut = packed;
  cut.resize(cut.size() - 100);
  const DecodeResult r = decode_map(cut, Encoding::kOctomapBtZstd, {});
  EXPECT_EQ(r.error, DecodeError::kDecompressionFailed) << r.reason;
  EXPECT_EQ(decode_map(as_bytes("not zstd at all"), Encoding::kOctomapBtZstd, {}).error,
            DecodeError::kDecompressionFailed);
}

TEST(Codec, ReadOctreeFileValidatesToo) {
  EXPECT_THROW(read_octree_file(test::data_path("README.md")), MapError);
  EXPECT_THROW(read_octree_file(test::data_path("missing.bt")), MapError);
  const auto tree = read_octree_file(test::data_path("geb079.bt"));
  EXPECT_DOUBLE_EQ(tree->getResolution(), 0.08);
}

TEST(Codec, ReadMapFileChecksAsReadOctreeFileAndKeepsABtFilesBody) {
  EXPECT_THROW(read_map_file(test::data_path("README.md")), MapError);
  EXPECT_THROW(read_map_file(test::data_path("missing.bt")), MapError);
  const std::string dir = ::testing::TempDir();
  {
    auto bytes = file_bytes("geb079.bt");
    bytes.resize(bytes.size() - 7);  // a truncated body
    std::ofstream(dir + "cut.bt", std::ios::binary).write(reinterpret_cast<const char*>(bytes.data()), bytes.size());
  }
  EXPECT_THROW(read_octree_file(dir + "cut.bt"), MapError);
  EXPECT_THROW(read_map_file(dir + "cut.bt"), MapError);
  const auto held = read_map_file(test::data_path("geb079.bt"));
  ASSERT_TRUE(held->binary_body());
  EXPECT_FALSE(held->has_tree());
  EXPECT_DOUBLE_EQ(held->resolution(), 0.08);
  const auto tree = read_octree_file(test::data_path("geb079.bt"));
  EXPECT_EQ(held->num_nodes(), tree->size());
  EXPECT_EQ(held->tree()->size(), tree->size());
  write_octree_file(octomap::OcTree(0.05), dir + "empty.bt");
  const auto empty = read_map_file(dir + "empty.bt");  // empty but well-formed: a map without nodes
  EXPECT_EQ(empty->num_nodes(), 0U);
  EXPECT_DOUBLE_EQ(empty->resolution(), 0.05);
  write_octree_file(*tree, dir + "geb079.ot");
  const auto full = read_map_file(dir + "geb079.ot");  // kept as its full body
  EXPECT_FALSE(full->binary_body());
  ASSERT_TRUE(full->full_body());
  EXPECT_FALSE(full->has_tree());
  EXPECT_EQ(full->num_nodes(), tree->size());
  EXPECT_EQ(full->tree()->size(), tree->size());
}

/// OctoMap's own extent (one leaf iteration per call) against leaf_bounds().
void expect_octomap_bounds(const octomap::OcTree& tree, const std::string& what) {
  double x0, y0, z0, x1, y1, z1;
  tree.getMetricMin(x0, y0, z0);
  tree.getMetricMax(x1, y1, z1);
  const Eigen::AlignedBox3d b = leaf_bounds(tree);
  ASSERT_FALSE(b.isEmpty()) << what;
  const double eps = 1e-6;
  EXPECT_NEAR(b.min().x(), x0, eps) << what;
  EXPECT_NEAR(b.min().y(), y0, eps) << what;
  EXPECT_NEAR(b.min().z(), z0, eps) << what;
  EXPECT_NEAR(b.max().x(), x1, eps) << what;
  EXPECT_NEAR(b.max().y(), y1, eps) << what;
  EXPECT_NEAR(b.max().z(), z1, eps) << what;
  // The same box read off the map's payload bytes, without building its tree.
  const CheckedMap held = check_map(encode_map(tree, Encoding::kOctomapBt), "octomap-bt", DecodeLimits{});
  ASSERT_TRUE(held.map) << what << ": " << held.reason;
  const Eigen::AlignedBox3d from_body = leaf_bounds(*held.map);
  EXPECT_FALSE(held.map->has_tree()) << what;
  EXPECT_TRUE(from_body.min() == b.min() && from_body.max() == b.max()) << what;
}

TEST(Bounds, LeafBoundsAreOctomapsExtentOnRealMapsAndTheirParts) {
  for (const char* name : kMaps) {
    const auto tree = read_octree_file(test::data_path(name));
    expect_octomap_bounds(*tree, name);
    // A part moved off the origin (negative and positive keys, pruned blocks at the faces).
    const auto part = crop_and_transform(*tree, Eigen::AlignedBox3d(Eigen::Vector3d(-3, -2, -1), Eigen::Vector3d(4, 2.5, 1.5)),
                                         Eigen::Isometry3d(Eigen::Translation3d(-7.3, 11.1, 0.4)));
    part->prune();
    expect_octomap_bounds(*part, std::string(name) + " part");
  }
  // One pruned leaf: a whole block of 8x8x8 voxels.
  octomap::OcTree block(0.1);
  for (int x = 0; x < 8; ++x)
    for (int y = 0; y < 8; ++y)
      for (int z = 0; z < 8; ++z) block.updateNode(octomap::OcTreeKey(32768 + x, 32760 + y, 32768 + z), true);
  block.prune();
  ASSERT_LT(block.getNumLeafNodes(), 8u);
  expect_octomap_bounds(block, "block");
  const Eigen::AlignedBox3d b = leaf_bounds(block);
  EXPECT_NEAR(b.min().y(), -0.8, 1e-9);
  EXPECT_NEAR(b.max().x(), 0.8, 1e-9);
  EXPECT_TRUE(leaf_bounds(octomap::OcTree(0.05)).isEmpty());
}


/// The occupied and the free leaves read off a map's bytes against its octree, voxel by voxel.
void expect_leaf_sets_match(const octomap::OcTree& tree, const std::string& what) {
  const CheckedMap held = check_map(encode_map(tree, Encoding::kOctomapBt), "octomap-bt", DecodeLimits{});
  ASSERT_TRUE(held.map) << what << ": " << held.reason;
  const auto leaves = held.map->occupied_leaves();
  const LeafSet free_leaves = LeafSet::of(*held.map, LeafState::kFree);
  EXPECT_FALSE(held.map->has_tree()) << what;
  for (const bool occupied : {true, false}) {
    const LeafSet& from_body = occupied ? *leaves : free_leaves;
    const LeafSet from_tree = LeafSet::of(tree, occupied ? LeafState::kOccupied : LeafState::kFree);
    const std::string kind = what + (occupied ? " occupied" : " free");
    std::size_t count = 0;
    for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) count += tree.isNodeOccupied(*it) == occupied;
    ASSERT_EQ(from_body.size(), count) << kind;
    ASSERT_EQ(from_tree.size(), count) << kind;
    // Every leaf centre read back is the centre of a leaf of the tree in that state, in the same
    // order for both readings.
    for (std::size_t i = 0; i < from_body.size(); i += 7) {
      const Eigen::Vector3d c = from_body.centre(i);
      EXPECT_TRUE(c.isApprox(from_tree.centre(i), 1e-12)) << kind << " leaf " << i;
      const octomap::OcTreeNode* n = tree.search(c.x(), c.y(), c.z());
      ASSERT_NE(n, nullptr) << kind << " leaf " << i;
      EXPECT_EQ(tree.isNodeOccupied(n), occupied) << kind << " leaf " << i;
    }
  }
  // Points anywhere in the box: occupied, free or unknown exactly where the tree says so.
  const double r = tree.getResolution();
  const Eigen::AlignedBox3d box = leaf_bounds(tree);
  std::size_t checked = 0, hits = 0, free_hits = 0;
  const Eigen::Vector3d step = (box.max() - box.min()) / 40.0;
  for (int i = 0; i <= 40; ++i)
    for (int j = 0; j <= 40; ++j)
      for (int k = 0; k <= 40; ++k) {
        const Eigen::Vector3d p = box.min() + Eigen::Vector3d(i * step.x(), j * step.y(), k * step.z()) +
                                  Eigen::Vector3d::Constant(0.3 * r);
        const octomap::OcTreeNode* n = tree.search(p.x(), p.y(), p.z());
        const bool in_tree = n != nullptr && tree.isNodeOccupied(n);
        const bool free_in_tree = n != nullptr && !tree.isNodeOccupied(n);
        ASSERT_EQ(leaves->contains(p), in_tree) << what << " at " << p.transpose();
        ASSERT_EQ(free_leaves.contains(p), free_in_tree) << what << " at " << p.transpose();
        ++checked;
        hits += in_tree;
        free_hits += free_in_tree;
      }
  EXPECT_GT(checked, 60000u);
  EXPECT_GT(hits, 0u) << what;
  EXPECT_GT(free_hits, 0u) << what;
  EXPECT_FALSE(leaves->contains(Eigen::Vector3d(1e6, 0, 0))) << what;  // off the key range
}

TEST(LeafSet, ReadOffTheBytesTheyAreTheTreesLeavesAndTellOccupancyAsItDoes) {
  for (const char* name : kMaps) {
    const auto tree = read_octree_file(test::data_path(name));
    expect_leaf_sets_match(*tree, name);
    const auto part = crop_and_transform(*tree, Eigen::AlignedBox3d(Eigen::Vector3d(-3, -2, -1), Eigen::Vector3d(4, 2.5, 1.5)),
                                         Eigen::Isometry3d(Eigen::Translation3d(-7.3, 11.1, 0.4)));
    part->prune();
    expect_leaf_sets_match(*part, std::string(name) + " part");
  }
  octomap::OcTree block(0.1);  // one pruned occupied leaf of 8x8x8 voxels, and a lone voxel
  for (int x = 0; x < 8; ++x)
    for (int y = 0; y < 8; ++y)
      for (int z = 0; z < 8; ++z) block.updateNode(octomap::OcTreeKey(32768 + x, 32760 + y, 32768 + z), true);
  block.updateNode(octomap::OcTreeKey(32700, 32800, 32790), true);
  for (int x = 0; x < 8; ++x)  // and 8x8x8 free voxels beside it
    for (int y = 0; y < 8; ++y)
      for (int z = 0; z < 8; ++z) block.updateNode(octomap::OcTreeKey(32776 + x, 32760 + y, 32768 + z), false);
  block.prune();
  expect_leaf_sets_match(block, "block");
  const LeafSet leaves = LeafSet::of(block, LeafState::kOccupied);
  EXPECT_EQ(leaves.size(), 2u);
  EXPECT_TRUE(leaves.contains(Eigen::Vector3d(0.05, -0.75, 0.75)));
  EXPECT_FALSE(leaves.contains(Eigen::Vector3d(0.85, -0.75, 0.75)));
  EXPECT_TRUE(LeafSet::of(block, LeafState::kFree).contains(Eigen::Vector3d(0.85, -0.75, 0.75)));
  EXPECT_EQ(LeafSet::of(block, LeafState::kFree).size(), 1u);
  EXPECT_EQ(LeafSet::of(octomap::OcTree(0.05), LeafState::kOccupied).size(), 0u);
}

TEST(LeafSet, OverlapIsFullOnItselfNoneFarAwayAndFollowsTheTransform) {
  const auto tree = read_octree_file(test::data_path("geb079.bt"));
  const LeafSet whole = LeafSet::of(*tree, LeafState::kOccupied);
  Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
  EXPECT_DOUBLE_EQ(estimate_overlap(whole, whole, T, 1000), 1.0);
  T(0, 3) = 500.0;
  EXPECT_DOUBLE_EQ(estimate_overlap(whole, whole, T, 1000), 0.0);
  // A part of the map, moved: with the inverse motion it lies on the whole map; without, it
  // mostly does not.
  const Eigen::Isometry3d moved(Eigen::Translation3d(3.1, -2.2, 0.0) * Eigen::AngleAxisd(0.7, Eigen::Vector3d::UnitZ()));
  const auto part = crop_and_transform(*tree, Eigen::AlignedBox3d(Eigen::Vector3d(-5, -5, -2), Eigen::Vector3d(5, 5, 3)), moved);
  const LeafSet p = LeafSet::of(*part, LeafState::kOccupied);
  ASSERT_GT(p.size(), 1000u);
  EXPECT_GT(estimate_overlap(whole, p, moved.inverse().matrix(), 1000), 0.9);
  EXPECT_LT(estimate_overlap(whole, p, Eigen::Matrix4d::Identity(), 1000), 0.5);
  EXPECT_EQ(estimate_overlap(whole, LeafSet::of(octomap::OcTree(0.08), LeafState::kOccupied), T, 1000), 0.0);
}

}  // namespace
}  // namespace mapmerge
