#include "mapmerge/map/global_fusion.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <mutex>
#include <unordered_map>
#include <utility>

#include "leaf_mapper.hpp"
#include "mapmerge/map/bounds.hpp"
#include "mapmerge/map/map_io.hpp"
#include "morton.hpp"
#include "parallel.hpp"
#include "sum_tree.hpp"
#include "body_leaves.hpp"
#include "tree_scan.hpp"

namespace mapmerge {
namespace {

using detail::kTreeDepth;

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

/// One robot's packed evidence for a leaf of log-odds `v` (0: ignored, as fuse_into ignores it).
std::int64_t evidence(float v, const FuseConfig& config) {
  return v < 0.0F && !config.fuse_free ? 0 : detail::pack_evidence(v);
}

/// Grows `box` by the cube of `size` [m] about `centre`.
void grow(Eigen::AlignedBox3d& box, const Eigen::Vector3d& centre, double size) {
  const Eigen::Vector3d half = Eigen::Vector3d::Constant(0.5 * size);
  box.extend(centre - half);
  box.extend(centre + half);
}

/// Why a map whose fusion would cost `work` voxel visits (more than FuseConfig::max_work) is refused.
std::string work_refusal(double work) {
  return "map would cost ~" + std::to_string(static_cast<long long>(work)) +
         " voxel visits, more than max_work (huge pruned leaves?)";
}

/// A region of a robot map's frame whose evidence changed, as a cube of the map's grid.
struct ChangedCube {
  Eigen::Vector3d centre;
  double size = 0.0;
  std::int64_t delta = 0;
};

/// One side of the simultaneous walk over two trees: a node, or a uniform value inherited from a
/// leaf above (with `node` null), or nothing (`known` false).
struct Side {
  const octomap::OcTreeNode* node = nullptr;
  bool known = false;
  float value = 0.0F;
};

/// Walks the old and the new map of a robot (same resolution, same frame) together and lists
/// where their evidence differs; sums the new map's fusion work on the way.
class TreeDiff {
 public:
  TreeDiff(const octomap::OcTree& before, const octomap::OcTree& after, double target_res,
           const FuseConfig& config)
      : before_(before), after_(after), target_res_(target_res), config_(config) {}

  void run() {
    Side a{before_.getRoot(), before_.getRoot() != nullptr};
    Side b{after_.getRoot(), after_.getRoot() != nullptr};
    walk(a, b, octomap::OcTreeKey(32768, 32768, 32768), 0);
  }
  std::vector<ChangedCube> cubes;
  double work = 0.0;  ///< fusion work of the new map (FuseConfig::max_work's measure)

 private:
  /// A node without children is a uniform block from here down.
  Side settle(Side s, const octomap::OcTree& tree, unsigned depth, bool count_work) {
    if (s.node == nullptr || tree.nodeHasChildren(s.node)) return s;
    s.value = s.node->getLogOdds();
    s.node = nullptr;
    if (count_work && (s.value >= 0.0F || config_.fuse_free)) {
      work += detail::leaf_fusion_work(std::max(1.0, std::ceil(tree.getNodeSize(depth) / target_res_)));
    }
    return s;
  }

  static Side child(const octomap::OcTree& tree, const Side& s, unsigned i) {
    if (s.node == nullptr) return s;  // nothing, or a uniform block: the same for every child
    if (!tree.nodeChildExists(s.node, i)) return Side{};
    return Side{tree.getNodeChild(s.node, i), true};
  }

  void walk(Side a, Side b, const octomap::OcTreeKey& key, unsigned depth) {
    a = settle(a, before_, depth, false);
    b = settle(b, after_, depth, true);
    if (a.node == nullptr && b.node == nullptr) {
      const std::int64_t ea = a.known ? evidence(a.value, config_) : 0;
      const std::int64_t eb = b.known ? evidence(b.value, config_) : 0;
      if (ea != eb) {
        const double c[3] = {after_.keyToCoord(key[0], depth), after_.keyToCoord(key[1], depth),
                             after_.keyToCoord(key[2], depth)};
        cubes.push_back({Eigen::Vector3d(c[0], c[1], c[2]), after_.getNodeSize(depth), eb - ea});
      }
      return;
    }
    const auto offset = static_cast<octomap::key_type>(32768 >> (depth + 1));
    for (unsigned i = 0; i < 8; ++i) {
      octomap::OcTreeKey k;
      octomap::computeChildKey(i, offset, key, k);
      walk(child(before_, a, i), child(after_, b, i), k, depth + 1);  // depth <= 16
    }
  }

  const octomap::OcTree& before_;
  const octomap::OcTree& after_;
  double target_res_;
  const FuseConfig& config_;
};

/// The same difference as TreeDiff, read off the binary bodies the two trees were decoded from
/// (OcTree::writeBinaryData: per inner node 2 bytes of 8 two-bit child codes, depth-first): one
/// sequential pass over the bytes instead of chasing two trees' pointers. Leaves of a body carry
/// the log-odds its tree's reader gave them (the tree's clamping bounds). The bodies are
/// validated (decode_map's pre-pass), so the recursion is at most 16 deep and never reads past
/// their ends.
class BodyDiff {
 public:
  /// A null side is an empty map: the difference is then the other map's whole evidence (taken
  /// out when `after` is null). `emit`, if given, gets each cube instead of `cubes`.
  BodyDiff(const HeldMap* before, const HeldMap* after, double target_res, const FuseConfig& config,
           std::function<void(const ChangedCube&)> emit = nullptr)
      : a_(before != nullptr ? *before->binary_body() : no_body()),
        b_(after != nullptr ? *after->binary_body() : no_body()),
        resolution_(after != nullptr ? after->resolution() : before->resolution()),
        target_res_(target_res),
        config_(config),
        emit_(std::move(emit)) {
    if (before != nullptr) {
      ea_[kFree] = evidence(before->free_log_odds(), config);
      ea_[kOccupied] = evidence(before->occupied_log_odds(), config);
    }
    if (after != nullptr) {
      eb_[kFree] = evidence(after->free_log_odds(), config);
      eb_[kOccupied] = evidence(after->occupied_log_odds(), config);
    }
    for (unsigned depth = 0; depth <= kTreeDepth; ++depth) {  // per leaf, as TreeDiff counts it
      leaf_work_[depth] = detail::leaf_fusion_work(std::max(1.0, std::ceil(node_size(depth) / target_res_)));
    }
  }

  /// False when a body is not a complete tree (not what decode_map validated): then nothing
  /// read is meaningful and the caller walks the trees instead.
  bool run() {
    const octomap::OcTreeKey root(32768, 32768, 32768);
    std::size_t pa = 0, pb = 0;
    if (!a_.empty() && !b_.empty()) {
      both(pa, pb, root, 0);
    } else if (!b_.empty()) {
      one_side(false, pb, root, 0, kUnknown);
    } else if (!a_.empty()) {
      one_side(true, pa, root, 0, kUnknown);
    }
    return ok_ && pa == a_.size() && pb == b_.size();
  }
  std::vector<ChangedCube> cubes;
  std::vector<ChangedCube> cubes_after;  ///< the parts from set_split()'s code on
  double work = 0.0;  ///< fusion work of the new map (as TreeDiff counts it)

  /// The walk's order as Morton codes of the finest keys (morton.hpp): a cube at depth d holds
  /// the codes [code of its lowest key, + 8^(16-d)). This is the end of that order.
  static constexpr std::uint64_t kOrderEnd = std::uint64_t{1} << (3 * kTreeDepth);

  /// Gives only the parts of changed cubes in [from, to) (a cube across either end is cut into
  /// its octants, as far down as needed), at most `limit` of them: the window then ends where
  /// the last one ends. The walk stops at the first changed cube past the window (run() then
  /// returns false: the bodies were not read to their ends). A move in steps walks each step's
  /// slice this way, not the whole body.
  void set_window(std::uint64_t from, std::uint64_t to, std::size_t limit) {
    from_ = from;
    to_ = to;
    limit_ = limit;
    windowed_ = true;
  }
  /// Where the window ends now (its `to`, or the end of its `limit`-th part).
  std::uint64_t window_end() const { return to_; }
  bool stopped() const { return stopped_; }  ///< the walk ended past the window
  /// The parts of changed cubes from `at` on go to cubes_after (cut there as set_window cuts).
  void set_split(std::uint64_t at) {
    split_ = at;
    windowed_ = true;
  }

 private:
  enum Code : unsigned { kUnknown = 0, kFree = 1, kOccupied = 2, kInner = 3 };

  /// Child i's code of the node record at pos (unknown, flagging the body, past its end).
  unsigned code(const std::vector<std::uint8_t>& body, std::size_t pos, unsigned i) {
    if (pos + 2 > body.size()) {
      ok_ = false;
      return kUnknown;
    }
    return detail::binary_child_code(body.data() + pos, i);
  }
  static octomap::OcTreeKey child_key(const octomap::OcTreeKey& key, unsigned depth, unsigned i) {
    octomap::OcTreeKey k;
    octomap::computeChildKey(i, static_cast<octomap::key_type>(32768 >> (depth + 1)), key, k);
    return k;
  }
  /// A leaf (or unknown space) of the new map at `depth`: its fusion work.
  void count(unsigned c, unsigned depth) {
    if (c == kOccupied || (c == kFree && config_.fuse_free)) work += leaf_work_[depth];
  }
  /// OcTree::getNodeSize and OcTree::keyToCoord(key, depth) of the new map's grid.
  double node_size(unsigned depth) const { return std::ldexp(resolution_, static_cast<int>(kTreeDepth - depth)); }
  double coord(octomap::key_type key, unsigned depth) const {
    if (depth == 0) return 0.0;
    const double k = static_cast<double>(key) - 32768.0;
    if (depth == kTreeDepth) return (k + 0.5) * resolution_;
    return (std::floor(k / static_cast<double>(1U << (kTreeDepth - depth))) + 0.5) * node_size(depth);
  }
  /// Two uniform values over the node at (key, depth): a cube where their evidence differs.
  void compare(unsigned ca, unsigned cb, const octomap::OcTreeKey& key, unsigned depth) {
    const std::int64_t ea = ca == kUnknown ? 0 : ea_[ca], eb = cb == kUnknown ? 0 : eb_[cb];
    if (ea != eb) deliver(key, depth, eb - ea);
  }
  /// A changed cube at (key, depth), or its parts, to the window, the split and the output.
  void deliver(const octomap::OcTreeKey& key, unsigned depth, std::int64_t delta) {
    if (!windowed_) {
      give(key, depth, delta, false);
      return;
    }
    const auto [lo, hi] = order_range(key, depth);
    if (hi <= from_) return;
    if (lo >= to_) {
      stopped_ = true;
      ok_ = false;  // ends the walk
      return;
    }
    if (lo < from_ || hi > to_ || (lo < split_ && split_ < hi)) {  // across a cut: its octants
      for (unsigned i = 0; i < 8 && ok_; ++i) deliver(child_key(key, depth, i), depth + 1, delta);
      return;
    }
    give(key, depth, delta, lo >= split_);
    if (++given_ >= limit_) to_ = hi;
  }
  void give(const octomap::OcTreeKey& key, unsigned depth, std::int64_t delta, bool after_split) {
    ChangedCube cube{Eigen::Vector3d(coord(key[0], depth), coord(key[1], depth), coord(key[2], depth)),
                     node_size(depth), delta};
    if (emit_) {
      emit_(cube);
    } else {
      (after_split ? cubes_after : cubes).push_back(cube);
    }
  }
  /// The codes [first, end) of the walk's order that the node at (key, depth) holds.
  static std::pair<std::uint64_t, std::uint64_t> order_range(const octomap::OcTreeKey& key, unsigned depth) {
    const unsigned shift = kTreeDepth - depth;
    const auto low = static_cast<octomap::key_type>(~((1U << shift) - 1U));  // the node's lowest key
    const std::uint64_t lo = detail::morton_code(key[0] & low, key[1] & low, key[2] & low);
    return {lo, lo + (std::uint64_t{1} << (3 * shift))};
  }
  static const std::vector<std::uint8_t>& no_body() {
    static const std::vector<std::uint8_t> empty;
    return empty;
  }
  /// Both maps have an inner node at (key, depth), at pa and pb.
  void both(std::size_t& pa, std::size_t& pb, const octomap::OcTreeKey& key, unsigned depth) {
    if (depth > 15) ok_ = false;  // an inner node below the last level
    if (!ok_) return;
    if (depth == kSkipDepth && same_subtree(pa, pb, depth)) return;
    const std::size_t na = pa, nb = pb;
    pa += 2;
    pb += 2;
    for (unsigned i = 0; i < 8; ++i) {
      const unsigned ca = code(a_, na, i), cb = code(b_, nb, i);
      const octomap::OcTreeKey k = child_key(key, depth, i);
      if (ca == kInner && cb == kInner) {
        both(pa, pb, k, depth + 1);
      } else if (ca == kInner) {
        count(cb, depth + 1);
        one_side(true, pa, k, depth + 1, cb);
      } else if (cb == kInner) {
        one_side(false, pb, k, depth + 1, ca);
      } else {
        count(cb, depth + 1);
        compare(ca, cb, k, depth + 1);
      }
    }
  }
  /// Where most of a grown map's blocks (subtrees at this depth, 1.6 m at 5 cm) are byte for
  /// byte what they were: such a block is skipped with one memcmp after counting its length.
  static constexpr unsigned kSkipDepth = 11;
  /// Set bits of a mask of the even bits of 16 (the base ISA has no popcount instruction).
  static unsigned ones(unsigned even_bits) {
    unsigned x = (even_bits & 0x3333U) + ((even_bits >> 2) & 0x3333U);
    x = (x & 0x0F0FU) + ((x >> 4) & 0x0F0FU);
    return (x & 0xFFU) + (x >> 8);
  }
  /// If the subtrees at pa (old body) and pb (new body), both at `depth`, are the same bytes:
  /// moves past them, adds the new one's fusion work, and returns true (no evidence changed).
  bool same_subtree(std::size_t& pa, std::size_t& pb, unsigned depth) {
    if (pa + 2 > a_.size() || pb + 2 > b_.size() || a_[pa] != b_[pb] || a_[pa + 1] != b_[pb + 1]) return false;
    if (ea_[kFree] != eb_[kFree] || ea_[kOccupied] != eb_[kOccupied]) return false;  // same codes, other evidence
    std::size_t length = 0;
    double w = 0.0;
    if (!scan_subtree(a_, pa, depth, length, w)) return false;  // not a complete tree: let the walk flag it
    if (pb + length > b_.size() || std::memcmp(a_.data() + pa, b_.data() + pb, length) != 0) return false;
    pa += length;
    pb += length;
    work += w;
    return true;
  }
  /// The length [bytes] of the subtree whose root record (a node at `depth`) is at `pos` of
  /// `body`, and the fusion work of its leaves (as the new map's), read level by level (a pending
  /// count per depth) without a walk. False when the body ends first or nests too deep.
  bool scan_subtree(const std::vector<std::uint8_t>& body, std::size_t pos, unsigned depth, std::size_t& length,
                    double& w) const {
    std::array<std::uint32_t, kTreeDepth + 2> pending{};
    pending[depth] = 1;
    unsigned d = depth;
    const std::size_t start = pos;
    w = 0.0;
    for (;;) {
      while (d >= depth && pending[d] == 0) --d;
      if (d < depth || d > kTreeDepth) break;
      --pending[d];
      if (pos + 2 > body.size() || d >= kTreeDepth) return false;
      const unsigned r = body[pos] | unsigned{body[pos + 1]} << 8;
      pos += 2;
      const unsigned lo = r & 0x5555U, hi = (r >> 1) & 0x5555U;
      const unsigned inner = ones(lo & hi), occupied = ones(hi & ~lo), free = ones(lo & ~hi);
      w += leaf_work_[d + 1] * static_cast<double>(occupied + (config_.fuse_free ? free : 0U));
      if (inner > 0) pending[++d] = static_cast<std::uint32_t>(inner);
    }
    length = pos - start;
    return true;
  }
  /// One map (`before` or not) has an inner node at (key, depth), at pos; the other is uniform
  /// (`other`: unknown, free or occupied) over it.
  void one_side(bool before, std::size_t& pos, const octomap::OcTreeKey& key, unsigned depth, unsigned other) {
    if (depth > 15) ok_ = false;
    if (!ok_) return;
    const std::vector<std::uint8_t>& body = before ? a_ : b_;
    if (from_ > 0 && order_range(key, depth).second <= from_) {  // before the window: only its length
      std::size_t length = 0;
      double w = 0.0;
      if (!scan_subtree(body, pos, depth, length, w)) {
        ok_ = false;
        return;
      }
      pos += length;
      if (!before) work += w;
      return;
    }
    const std::size_t node = pos;
    pos += 2;
    for (unsigned i = 0; i < 8; ++i) {
      const unsigned c = code(body, node, i);
      const octomap::OcTreeKey k = child_key(key, depth, i);
      if (c == kInner) {
        one_side(before, pos, k, depth + 1, other);
        continue;
      }
      if (!before) count(c, depth + 1);
      before ? compare(c, other, k, depth + 1) : compare(other, c, k, depth + 1);
    }
  }

  const std::vector<std::uint8_t>& a_;
  const std::vector<std::uint8_t>& b_;
  double resolution_;
  double target_res_;
  const FuseConfig& config_;
  std::function<void(const ChangedCube&)> emit_;
  std::uint64_t from_ = 0;
  std::uint64_t to_ = kOrderEnd;
  std::size_t limit_ = SIZE_MAX;
  std::size_t given_ = 0;  ///< parts given in the window
  std::uint64_t split_ = kOrderEnd;
  bool windowed_ = false;  ///< set_window() or set_split() called: cubes are placed in the order
  bool stopped_ = false;
  std::int64_t ea_[3] = {0, 0, 0};
  std::int64_t eb_[3] = {0, 0, 0};
  double leaf_work_[kTreeDepth + 1] = {};  ///< fusion work of one leaf of the new map, by depth
  bool ok_ = true;
};

/// Whether `map` has a binary body a BodyDiff walk can place on a grid of `target_res` (not
/// finer than the grid: finer leaves are voted per voxel, on the tree).
bool walkable_body(const HeldMap& map, double target_res) {
  return map.binary_body() && map.resolution() >= target_res * (1 - 1e-9);
}

/// A whole map's evidence read off its binary body (no tree): its fusion work (estimate_work's
/// measure) and, if `emit` is given, each leaf to it as a cube of +evidence (-evidence when
/// `remove`). False, with nothing emitted, when the map has no body, its body is not a complete
/// tree, or it is finer than the target grid (fine leaves are voted per voxel, on the tree).
/// `checked`: a call of this map without `emit` returned true already (its work is not counted).
bool whole_body(const HeldMap& map, bool remove, double target_res, const FuseConfig& config,
                const std::function<void(const ChangedCube&)>& emit, double& work, bool checked = false) {
  if (!walkable_body(map, target_res)) return false;
  const HeldMap* before = remove ? &map : nullptr;
  const HeldMap* after = remove ? nullptr : &map;
  if (!checked) {
    BodyDiff check(before, after, target_res, config, [](const ChangedCube&) {});  // all or nothing
    if (!check.run()) return false;
    work = check.work;
  }
  if (emit) BodyDiff(before, after, target_res, config, emit).run();
  return true;
}

/// Packed votes of source leaves finer than the target's voxels: the largest per voxel.
using FineVotes = std::unordered_map<octomap::OcTreeKey, float, octomap::OcTreeKey::KeyHash>;

/// An add the mapper found (a voxel, or an aligned block of 2^level voxels a side), held so that
/// a run of them can be sorted into the tree's depth-first order and sibling adds merged
/// (apply_in_tree_order): a turned map's cubes are cut into voxels along their faces (fr_079:
/// 2.5 adds a cube), and the merge takes most of those back into blocks. Sorting alone did not
/// make the placing faster; the merge does (bench/results/server.md, session 14).
struct PendingAdd {
  std::uint64_t order;  ///< Morton code of the key (morton.hpp), shifted left by 4, | level
  std::int64_t delta;
};

/// The mapper's sink of a sorted placement: collects the adds.
struct PendingSink {
  std::vector<PendingAdd>& adds;
  void apply(const octomap::OcTreeKey& key, unsigned level, std::int64_t delta) {
    adds.push_back({detail::morton_code(key[0], key[1], key[2]) << 4 | level, delta});
  }
};

/// Sorts `adds` into depth-first order, merges each 8 of one level that are the children of
/// one block and add the same delta into one add of that block (up to a block of the encoder,
/// SumTree::kBlockDepth: the windows of map_cubes), and gives each to `add(key, level, delta)`.
/// The sums are integers and the adds' voxels are disjoint, so neither the order nor the merge
/// changes a voxel's sum; the encoder prunes what the merge does not create.
template <class Add>
void apply_in_tree_order(std::vector<PendingAdd>& adds, Add&& add) {
  constexpr unsigned kMaxLevel = kTreeDepth - detail::SumTree::kBlockDepth;
  std::sort(adds.begin(), adds.end(), [](const PendingAdd& a, const PendingAdd& b) { return a.order < b.order; });
  std::size_t n = 0;  // adds[0, n): the merged list so far, used as a stack
  for (const PendingAdd& next : adds) {
    adds[n++] = next;
    while (n >= 8) {
      const PendingAdd& first = adds[n - 8];
      const auto level = static_cast<unsigned>(first.order & 15U);
      const std::uint64_t code = first.order >> 4, step = std::uint64_t{1} << (3 * level);
      if (level >= kMaxLevel || (code & ((step << 3) - 1)) != 0) break;  // not a first child
      bool siblings = true;
      for (unsigned i = 1; i < 8 && siblings; ++i) {
        const PendingAdd& c = adds[n - 8 + i];
        siblings = c.order == ((code + i * step) << 4 | level) && c.delta == first.delta;
      }
      if (!siblings) break;
      adds[n - 8].order = code << 4 | (level + 1);
      n -= 7;
    }
  }
  adds.resize(n);
  for (const PendingAdd& p : adds) {
    const std::uint64_t code = p.order >> 4;
    const octomap::OcTreeKey key(static_cast<octomap::key_type>(detail::morton_compact(code)),
                                 static_cast<octomap::key_type>(detail::morton_compact(code >> 1)),
                                 static_cast<octomap::key_type>(detail::morton_compact(code >> 2)));
    add(key, static_cast<unsigned>(p.order & 15U), p.delta);
  }
  adds.clear();
}

/// One leaf of a map's octree, as add_full() reads it.
struct TreeLeaf {
  Eigen::Vector3d centre;
  double size = 0.0;
  float log_odds = 0.0F;
};

/// Calls `leaf` with every leaf of `tree`, in the order of its leaf iterator.
template <class Leaf>
void for_each_tree_leaf(const octomap::OcTree& tree, Leaf&& leaf) {
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    leaf(TreeLeaf{Eigen::Vector3d(it.getX(), it.getY(), it.getZ()), it.getSize(), it->getLogOdds()});
  }
}

/// Calls `leaf` with every leaf of a map's body, in the order of the leaf iterator of its tree
/// and with the same numbers (its tree is not built). False when the map holds no body.
template <class Leaf>
bool for_each_body_tree_leaf(const HeldMap& map, Leaf&& leaf) {
  const double res = map.resolution();
  return detail::for_each_body_leaf(map, [&](float log_odds, bool, unsigned depth, std::uint32_t x, std::uint32_t y,
                                             std::uint32_t z) {
    leaf(TreeLeaf{Eigen::Vector3d(detail::leaf_coord(x, depth, res), detail::leaf_coord(y, depth, res),
                                  detail::leaf_coord(z, depth, res)),
                  detail::leaf_size(depth, res), log_odds});
  });
}

/// estimate_work() of a map without a binary body: off its full body when it has one, else off
/// its tree.
double tree_map_work(const HeldMap& map, double target_res, bool fuse_free) {
  if (!map.full_body()) return detail::estimate_work(*map.tree(), target_res, fuse_free);
  double work = 0.0;
  detail::for_each_body_leaf(map, [&](float, bool occupied, unsigned depth, std::uint32_t, std::uint32_t,
                                      std::uint32_t) {
    work += detail::leaf_work(detail::leaf_size(depth, map.resolution()), occupied, target_res, fuse_free);
  });
  return work;
}

/// Fewer cubes than this are placed on the calling thread (a thread start costs more).
constexpr std::size_t kParallelCubes = 2048;

/// Places `cubes` (a robot map's frame, moved by `T`) into `sums`, each run of adds in the
/// tree's order (PendingAdd). With several threads and enough cubes, the target blocks
/// (SumTree::kBlockDepth subtrees) they reach are shared out: each block is written by one
/// thread with its own descent and node count, so the sums are the same as one thread's
/// (integer sums in another order) and so are the encoded bytes.
void map_cubes(detail::SumTree& sums, const Eigen::Matrix4d& T, double res, const std::vector<ChangedCube>& cubes,
               unsigned threads, FuseResult& counts) {
  std::vector<PendingAdd> adds;
  PendingSink sink{adds};
  detail::LeafMapper<PendingSink, std::int64_t> mapper(T, res, sink, counts);
  if (threads < 2 || cubes.size() < kParallelCubes) {
    for (const ChangedCube& cube : cubes) mapper.add_cube(cube.centre, cube.size, cube.delta);
    apply_in_tree_order(adds, [&](const octomap::OcTreeKey& key, unsigned level, std::int64_t delta) {
      sums.add(key, level, delta);
    });
    return;
  }
  // Which blocks each cube may reach (its key box, in blocks).
  constexpr unsigned kBlockLevel = kTreeDepth - detail::SumTree::kBlockDepth;
  std::unordered_map<std::uint64_t, std::vector<std::uint32_t>> by_block;
  for (std::size_t i = 0; i < cubes.size(); ++i) {
    int lo[3];
    int hi[3];
    if (!mapper.key_bounds(cubes[i].centre, cubes[i].size, lo, hi)) continue;
    for (int z = lo[2] >> kBlockLevel; z <= hi[2] >> kBlockLevel; ++z)
      for (int y = lo[1] >> kBlockLevel; y <= hi[1] >> kBlockLevel; ++y)
        for (int x = lo[0] >> kBlockLevel; x <= hi[0] >> kBlockLevel; ++x)
          by_block[patch_block_of(octomap::OcTreeKey(static_cast<octomap::key_type>(x << kBlockLevel),
                                                     static_cast<octomap::key_type>(y << kBlockLevel),
                                                     static_cast<octomap::key_type>(z << kBlockLevel)))]
              .push_back(static_cast<std::uint32_t>(i));
  }
  struct Job {
    std::uint64_t block;
    const std::vector<std::uint32_t>* cubes;
    bool changed = false;
  };
  std::vector<Job> jobs;
  jobs.reserve(by_block.size());
  for (const auto& [block, members] : by_block) jobs.push_back({block, &members});
  // Most cubes first: the longest jobs start early, the short ones fill in.
  std::sort(jobs.begin(), jobs.end(), [](const Job& a, const Job& b) {
    return a.cubes->size() != b.cubes->size() ? a.cubes->size() > b.cubes->size() : a.block < b.block;
  });
  for (const Job& job : jobs) sums.prepare_block(job.block);
  std::atomic<std::size_t> next{0};
  std::mutex done;
  auto work = [&] {
    detail::SumTree::BlockWriter writer(sums);
    std::vector<PendingAdd> mine_adds;
    PendingSink block_sink{mine_adds};
    FuseResult mine;
    detail::LeafMapper<PendingSink, std::int64_t> windowed(T, res, block_sink, mine);
    const auto add = [&](const octomap::OcTreeKey& key, unsigned level, std::int64_t delta) {
      writer.add(key, level, delta);
    };
    for (std::size_t k = next++; k < jobs.size(); k = next++) {
      windowed.set_window(patch_block_key(jobs[k].block), kBlockLevel);
      for (const std::uint32_t i : *jobs[k].cubes) windowed.add_cube(cubes[i].centre, cubes[i].size, cubes[i].delta);
      jobs[k].changed = !mine_adds.empty();
      apply_in_tree_order(mine_adds, add);
    }
    std::lock_guard<std::mutex> lock(done);
    sums.account_writer(writer);
    counts.voxel_updates += mine.voxel_updates;
    counts.block_updates += mine.block_updates;
  };
  detail::run_parallel(std::min<unsigned>(threads, static_cast<unsigned>((jobs.size() + 3) / 4)), work);
  for (const Job& job : jobs) {
    if (job.changed) sums.note_block(job.block);
  }
}

/// map_cubes() of `cubes` with their evidence times `sign` (+1: put in, -1: taken out).
void place_cubes(detail::SumTree& sums, const Eigen::Matrix4d& T, double res, const std::vector<ChangedCube>& cubes,
                 int sign, unsigned threads, FuseResult& counts) {
  if (sign > 0) {
    map_cubes(sums, T, res, cubes, threads, counts);
    return;
  }
  std::vector<ChangedCube> negated = cubes;
  for (ChangedCube& c : negated) c.delta = -c.delta;
  map_cubes(sums, T, res, negated, threads, counts);
}

/// A leaf as stage() keeps it: its key and depth in the map's tree, 12 B instead of TreeLeaf's
/// 40 (a `.ot` map of 0.8 M leaves: ~9 MB instead of ~31 MB of fresh pages). Its centre and
/// size are the tree's keyToCoord() and getNodeSize() of them, as the leaf iterator gives them.
struct StagedLeaf {
  octomap::OcTreeKey key;
  std::uint8_t depth = 0;
  float log_odds = 0.0F;
};

/// The TreeLeaf of a staged leaf of `tree`: the same numbers for_each_tree_leaf() gives.
TreeLeaf tree_leaf(const octomap::OcTree& tree, const StagedLeaf& l) {
  return TreeLeaf{Eigen::Vector3d(tree.keyToCoord(l.key[0], l.depth), tree.keyToCoord(l.key[1], l.depth),
                                  tree.keyToCoord(l.key[2], l.depth)),
                  tree.getNodeSize(l.depth), l.log_odds};
}

}  // namespace

struct GlobalFusion::StagedLeaves {
  std::shared_ptr<const HeldMap> map;
  double work = 0.0;  ///< estimate_work() of the map
  std::vector<StagedLeaf> leaves;
};

GlobalFusion::GlobalFusion(double resolution, const FuseConfig& config)
    : resolution_(resolution), config_(config) {
  if (!(resolution > 0.0) || !std::isfinite(resolution)) {
    throw MapError("GlobalFusion: resolution must be positive");
  }
  sums_ = std::make_unique<detail::SumTree>(resolution);
  encoded_ = std::make_unique<detail::EncodedBlocks>();
  threads_ = detail::default_threads();
}

void GlobalFusion::set_threads(unsigned threads) { threads_ = std::max(1U, threads); }

void GlobalFusion::stage(std::shared_ptr<const HeldMap> map) {
  staged_.reset();
  if (!map || walkable_body(*map, resolution_)) return;  // its body is read in one pass anyway
  auto staged = std::make_unique<StagedLeaves>();
  if (map->full_body()) {  // its leaves are read off the body when placed; its work now
    staged->work = tree_map_work(*map, resolution_, config_.fuse_free);
    staged->map = std::move(map);
    staged_ = std::move(staged);
    return;
  }
  const std::shared_ptr<const octomap::OcTree> tree = map->tree();
  // One walk gives the leaves and their work (estimate_work's sum). Room for every node: only
  // the pages the leaves fill are touched, and none is copied as the vector would grow.
  const float occupied = tree->getOccupancyThresLog();
  staged->leaves.reserve(map->num_nodes());
  for (auto it = tree->begin_leafs(), end = tree->end_leafs(); it != end; ++it) {
    const float log_odds = it->getLogOdds();
    staged->work += detail::leaf_work(it.getSize(), log_odds >= occupied, resolution_, config_.fuse_free);
    staged->leaves.push_back({it.getKey(), static_cast<std::uint8_t>(it.getDepth()), log_odds});
  }
  staged->map = std::move(map);
  staged_ = std::move(staged);
}

std::unique_ptr<GlobalFusion::StagedLeaves> GlobalFusion::take_staged(const HeldMap& map) {
  if (!staged_ || staged_->map.get() != &map) return nullptr;
  return std::move(staged_);
}

GlobalFusion::~GlobalFusion() = default;

bool GlobalFusion::empty() const { return robots_.empty(); }

std::vector<std::string> GlobalFusion::robots() const {
  std::vector<std::string> out;
  for (const auto& kv : robots_) out.push_back(kv.first);
  return out;
}

bool GlobalFusion::holds(const std::string& robot, const HeldMap* map,
                         const Eigen::Matrix4d& T) const {
  const auto it = robots_.find(robot);
  return it != robots_.end() && it->second.map.get() == map && it->second.T_global_robot == T && !it->second.T_to;
}

bool GlobalFusion::moving(const std::string& robot) const {
  const auto it = robots_.find(robot);
  return it != robots_.end() && it->second.T_to.has_value();
}

bool GlobalFusion::fuses_by_difference(const std::string& robot, const HeldMap& map) const {
  const auto it = robots_.find(robot);
  return it != robots_.end() && same_grid(it->second, map);
}

bool GlobalFusion::same_grid(const Entry& fused, const HeldMap& map) const {
  return fused.map->resolution() == map.resolution() && map.resolution() >= resolution_ * (1 - 1e-9);
}

std::optional<Eigen::Matrix4d> GlobalFusion::pose_of(const std::string& robot) const {
  const auto it = robots_.find(robot);
  if (it == robots_.end()) return std::nullopt;
  return it->second.pose();
}

std::shared_ptr<const HeldMap> GlobalFusion::map_of(const std::string& robot) const {
  const auto it = robots_.find(robot);
  return it == robots_.end() ? nullptr : it->second.map;
}

std::optional<Eigen::AlignedBox3d> GlobalFusion::extent_of(const std::string& robot) const {
  const auto it = robots_.find(robot);
  if (it == robots_.end()) return std::nullopt;
  return it->second.extent;
}

std::size_t GlobalFusion::memory_usage() const { return sums_->memoryUsage(); }

std::uint64_t GlobalFusion::add_leaves(const HeldMap& map, std::uint64_t from, std::uint64_t to, std::size_t limit,
                                       std::initializer_list<Placement> at, GlobalFuseResult& stats) {
  FuseResult counts;
  constexpr std::size_t kRun = std::size_t{1} << 16;
  std::vector<ChangedCube> run;
  const auto flush = [&] {
    for (const Placement& p : at) place_cubes(*sums_, *p.T, resolution_, run, p.sign, threads_, counts);
    run.clear();
  };
  const auto add = [&](const ChangedCube& cube) {
    ++stats.cubes;
    run.push_back(cube);
    if (run.size() >= kRun) flush();
  };
  if (!walkable_body(map, resolution_)) {
    throw MapError("GlobalFusion: a map moved in steps has no checked body");  // set() checked it
  }
  // Only the slice is walked to (its cubes' coordinates computed, given to `add`); the walk stops
  // after it.
  BodyDiff walk(nullptr, &map, resolution_, config_, add);
  walk.set_window(from, to, limit);
  walk.run();
  flush();
  stats.voxel_updates += counts.voxel_updates;
  stats.block_updates += counts.block_updates;
  return walk.stopped() ? walk.window_end() : BodyDiff::kOrderEnd;
}

void GlobalFusion::move_step(Entry& entry, std::size_t step, GlobalFuseResult& stats) {
  const auto t0 = std::chrono::steady_clock::now();
  entry.boundary = add_leaves(*entry.map, entry.boundary, BodyDiff::kOrderEnd, std::max<std::size_t>(step, 1),
                              {{&entry.T_global_robot, -1}, {&*entry.T_to, +1}}, stats);
  if (entry.boundary >= BodyDiff::kOrderEnd) {
    entry.T_global_robot = *entry.T_to;
    entry.T_to.reset();
    entry.boundary = 0;
  }
  stats.place_s += seconds_since(t0);
  stats.moving = entry.T_to.has_value();
}

GlobalFusion::Difference GlobalFusion::add_moving_difference(Entry& moving, std::shared_ptr<const HeldMap> map,
                                                            GlobalFuseResult& stats) {
  if (!moving.map->binary_body() || !map->binary_body()) return Difference::kTooFar;
  const auto t0 = std::chrono::steady_clock::now();
  BodyDiff diff(moving.map.get(), map.get(), resolution_, config_);
  diff.set_split(moving.boundary);
  if (!diff.run()) return Difference::kTooFar;
  stats.from_bodies = true;
  stats.work = diff.work;
  stats.diff_s += seconds_since(t0);
  if (diff.work > config_.max_work) {
    stats.reason = work_refusal(diff.work);
    return Difference::kRefused;
  }
  const auto t1 = std::chrono::steady_clock::now();
  FuseResult counts;
  map_cubes(*sums_, *moving.T_to, resolution_, diff.cubes, threads_, counts);  // the part moved already
  map_cubes(*sums_, moving.T_global_robot, resolution_, diff.cubes_after, threads_, counts);  // still at the old pose
  for (const auto* cubes : {&diff.cubes, &diff.cubes_after}) {
    for (const ChangedCube& c : *cubes) grow(moving.extent, c.centre, c.size);
    stats.cubes += cubes->size();
  }
  moving.map = std::move(map);
  stats.place_s += seconds_since(t1);
  stats.voxel_updates += counts.voxel_updates;
  stats.block_updates += counts.block_updates;
  return Difference::kPlaced;
}

bool GlobalFusion::place_on_own_grid(const HeldMap& map, const Eigen::Matrix4d& T, int sign, GlobalFuseResult& stats,
                                     Eigen::AlignedBox3d* extent, const StagedLeaves* staged) {
  if (map.resolution() != resolution_ || T != Eigen::Matrix4d::Identity()) return false;
  // Each leaf is an aligned block of the sums' grid: added as it is, nothing resampled (the same
  // sums as map_cubes() gives, and so the same bytes).
  const double res = resolution_;
  std::size_t voxels = 0, blocks = 0;
  const auto place = [&](float log_odds, bool, unsigned depth, std::uint32_t x, std::uint32_t y, std::uint32_t z) {
    const std::int64_t e = evidence(log_odds, config_);
    if (e == 0) return;
    ++stats.cubes;
    if (extent) {
      grow(*extent,
           Eigen::Vector3d(detail::leaf_coord(x, depth, res), detail::leaf_coord(y, depth, res),
                           detail::leaf_coord(z, depth, res)),
           detail::leaf_size(depth, res));
    }
    const unsigned level = kTreeDepth - depth;
    sums_->add(octomap::OcTreeKey(static_cast<octomap::key_type>(x), static_cast<octomap::key_type>(y),
                                  static_cast<octomap::key_type>(z)),
               level, sign * e);
    ++(level == 0 ? voxels : blocks);
  };
  if (!detail::for_each_body_leaf(map, place)) {
    const auto leaf = [&](const octomap::OcTreeKey& key, unsigned depth, float log_odds) {
      const std::uint32_t corner = ~((1U << (kTreeDepth - depth)) - 1U);  // the iterator's key is inside
      place(log_odds, detail::occupied_log_odds(log_odds), depth, key[0] & corner, key[1] & corner, key[2] & corner);
    };
    if (staged) {
      for (const StagedLeaf& l : staged->leaves) leaf(l.key, l.depth, l.log_odds);
    } else {
      const std::shared_ptr<const octomap::OcTree> tree = map.tree();
      for (auto it = tree->begin_leafs(), end = tree->end_leafs(); it != end; ++it)
        leaf(it.getKey(), it.getDepth(), it->getLogOdds());
    }
  }
  stats.voxel_updates += voxels;
  stats.block_updates += blocks;
  return true;
}

void GlobalFusion::add_full(const Entry& entry, int sign, GlobalFuseResult& stats, bool body_checked,
                            Eigen::AlignedBox3d* extent, const StagedLeaves* staged) {
  if (entry.T_to) {  // halfway through a move in steps: each part at its pose
    add_leaves(*entry.map, 0, entry.boundary, SIZE_MAX, {{&*entry.T_to, sign}}, stats);
    add_leaves(*entry.map, entry.boundary, BodyDiff::kOrderEnd, SIZE_MAX, {{&entry.T_global_robot, sign}}, stats);
    return;
  }
  const Eigen::Matrix4d& T = entry.T_global_robot;
  if (place_on_own_grid(*entry.map, T, sign, stats, extent, staged)) return;
  FuseResult counts;
  double work = 0.0;
  // The map's cubes go to map_cubes() in runs of kRun (memory stays bounded; each run is spread
  // over the threads).
  constexpr std::size_t kRun = std::size_t{1} << 16;
  std::vector<ChangedCube> run;
  const auto add = [&](const ChangedCube& cube) {
    ++stats.cubes;
    if (extent) grow(*extent, cube.centre, cube.size);
    run.push_back(cube);
    if (run.size() < kRun) return;
    map_cubes(*sums_, T, resolution_, run, threads_, counts);
    run.clear();
  };
  if (whole_body(*entry.map, sign < 0, resolution_, config_, add, work, body_checked)) {  // no tree built
    map_cubes(*sums_, T, resolution_, run, threads_, counts);
    stats.voxel_updates += counts.voxel_updates;
    stats.block_updates += counts.block_updates;
    return;
  }
  FineVotes fine;
  const auto place = [&](const TreeLeaf& leaf) {
    const std::int64_t e = evidence(leaf.log_odds, config_);
    if (e == 0) return;
    if (leaf.size >= resolution_ * (1 - 1e-9)) {
      add({leaf.centre, leaf.size, sign * e});
      return;
    }
    ++stats.cubes;  // a leaf finer than the grid: voted per voxel
    if (extent) grow(*extent, leaf.centre, leaf.size);
    const Eigen::Vector3d ct = T.topLeftCorner<3, 3>() * leaf.centre + T.topRightCorner<3, 1>();
    octomap::OcTreeKey key;
    if (!sums_->coordToKeyChecked(ct.x(), ct.y(), ct.z(), key)) return;
    auto [vote, inserted] = fine.try_emplace(key, leaf.log_odds);
    if (!inserted) vote->second = std::max(vote->second, leaf.log_odds);
  };
  if (entry.map->full_body()) {  // (a binary body not finer than the grid went through whole_body above)
    for_each_body_tree_leaf(*entry.map, place);
  } else if (staged) {
    const std::shared_ptr<const octomap::OcTree> tree = staged->map->tree();
    for (const StagedLeaf& leaf : staged->leaves) place(tree_leaf(*tree, leaf));
  } else {
    for_each_tree_leaf(*entry.map->tree(), place);
  }
  map_cubes(*sums_, T, resolution_, run, threads_, counts);
  for (const auto& [key, v] : fine) sums_->add(key, 0, sign * evidence(v, config_));
  stats.voxel_updates += counts.voxel_updates + fine.size();
  stats.block_updates += counts.block_updates;
}

GlobalFusion::Difference GlobalFusion::add_difference(const Entry& before, Entry& after, double keep_pose_within,
                                                     GlobalFuseResult& stats) {
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<ChangedCube> cubes;
  double work = 0.0;
  bool done = before.map == after.map;  // only the pose is new: nothing changed
  if (!done && before.map->binary_body() && after.map->binary_body()) {
    BodyDiff diff(before.map.get(), after.map.get(), resolution_, config_);
    if (diff.run()) {
      cubes = std::move(diff.cubes);
      work = diff.work;
      stats.from_bodies = done = true;
    }
  }
  if (!done) {
    const auto a = before.map->tree(), b = after.map->tree();
    TreeDiff diff(*a, *b, resolution_, config_);
    diff.run();
    cubes = std::move(diff.cubes);
    work = diff.work;
  }
  after.extent = before.extent;
  for (const ChangedCube& c : cubes) grow(after.extent, c.centre, c.size);
  stats.work = work;
  stats.diff_s += seconds_since(t0);
  if (work > config_.max_work) {
    stats.reason = work_refusal(work);
    return Difference::kRefused;
  }
  if (after.T_global_robot != before.T_global_robot) {
    if (!(max_displacement(before.T_global_robot, after.T_global_robot, after.extent) < keep_pose_within)) {
      return Difference::kTooFar;
    }
    after.T_global_robot = before.T_global_robot;
    stats.kept_pose = true;
  }
  const auto t1 = std::chrono::steady_clock::now();
  FuseResult counts;
  map_cubes(*sums_, after.T_global_robot, resolution_, cubes, threads_, counts);
  stats.place_s += seconds_since(t1);
  stats.cubes += cubes.size();
  stats.voxel_updates += counts.voxel_updates;
  stats.block_updates += counts.block_updates;
  return Difference::kPlaced;
}

GlobalFuseResult GlobalFusion::set(const std::string& robot, std::shared_ptr<const octomap::OcTree> map,
                                   const Eigen::Matrix4d& T_global_robot,
                                   std::shared_ptr<const std::vector<std::uint8_t>> binary_body) {
  return set(robot, map ? std::make_shared<const HeldMap>(std::move(map), std::move(binary_body)) : nullptr,
             T_global_robot);
}

GlobalFuseResult GlobalFusion::set(const std::string& robot, std::shared_ptr<const HeldMap> map,
                                   const Eigen::Matrix4d& T_global_robot, double keep_pose_within,
                                   std::size_t move_step) {
  GlobalFuseResult r;
  r.reason = map ? detail::check_rigid(T_global_robot, config_.rigid_tolerance) : "no map";
  if (!r.reason.empty()) {
    remove(robot);
    return r;
  }
  Entry next{std::move(map), T_global_robot, Eigen::AlignedBox3d(), std::nullopt, 0};
  const std::unique_ptr<StagedLeaves> staged = take_staged(*next.map);
  const auto it = robots_.find(robot);
  if (it != robots_.end() && it->second.T_to) {
    // A move in steps under way: its next step; or a new map of the same grid by its difference,
    // each part at the pose that part is fused at, and the move goes on with it from where it is
    // (no step in this call); or (another pose, no bodies to diff) the move's end at once.
    Entry& fused = it->second;
    if (move_step > 0 && *fused.T_to == T_global_robot) {
      if (fused.map == next.map) {
        this->move_step(fused, move_step, r);
        r.ok = true;
        return r;
      }
      if (same_grid(fused, *next.map)) {
        const Difference d = add_moving_difference(fused, next.map, r);
        if (d == Difference::kRefused) {
          remove(robot);
          return r;
        }
        if (d == Difference::kPlaced) {
          r.ok = r.incremental = r.moving = true;
          return r;
        }
      }
    }
    this->move_step(fused, SIZE_MAX, r);
  }
  if (it != robots_.end() && it->second.map == next.map && it->second.T_global_robot == T_global_robot) {
    r.ok = true;
    return r;
  }
  const bool by_difference = it != robots_.end() &&
                             (it->second.T_global_robot == T_global_robot || keep_pose_within > 0.0) &&
                             same_grid(it->second, *next.map);
  Difference diff = by_difference ? add_difference(it->second, next, keep_pose_within, r) : Difference::kTooFar;
  if (diff == Difference::kTooFar && by_difference && move_step > 0 && r.from_bodies) {
    // A new map whose pose moved too far to keep: its difference at the fused pose first (its
    // content goes out now), then the move in steps.
    diff = add_difference(it->second, next, std::numeric_limits<double>::infinity(), r);
    if (diff == Difference::kPlaced) {
      next.T_to = T_global_robot;
      it->second = std::move(next);
      this->move_step(it->second, move_step, r);
      r.ok = r.incremental = true;
      return r;
    }
  }
  if (diff != Difference::kTooFar) {
    r.ok = diff == Difference::kPlaced;
    r.incremental = r.ok;
  } else {
    r.from_bodies = false;  // fused whole
    const auto t0 = std::chrono::steady_clock::now();
    double work = 0.0;
    const bool body = whole_body(*next.map, false, resolution_, config_, nullptr, work);
    if (!body) work = staged ? staged->work : tree_map_work(*next.map, resolution_, config_.fuse_free);
    r.work = work;
    r.diff_s += seconds_since(t0);
    r.ok = work <= config_.max_work;
    if (!r.ok) {
      r.reason = work_refusal(work);
    } else if (move_step > 0 && body && it != robots_.end() && it->second.map == next.map) {
      // The same map at a new pose: moved in steps, this call the first (no move under way: the
      // first block ended it).
      it->second.T_to = T_global_robot;
      this->move_step(it->second, move_step, r);
      return r;
    } else {
      const auto t1 = std::chrono::steady_clock::now();
      if (it != robots_.end()) add_full(it->second, -1, r);
      next.extent.setEmpty();
      add_full(next, +1, r, body, &next.extent, staged.get());
      r.place_s += seconds_since(t1);
    }
  }
  if (!r.ok) {
    remove(robot);
    return r;
  }
  robots_[robot] = std::move(next);
  return r;
}

void GlobalFusion::remove(const std::string& robot) {
  const auto it = robots_.find(robot);
  if (it == robots_.end()) return;
  GlobalFuseResult ignored;
  add_full(it->second, -1, ignored);
  robots_.erase(it);
}

}  // namespace mapmerge
