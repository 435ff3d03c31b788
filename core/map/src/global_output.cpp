// GlobalFusion's outputs: the `.bt` payload (one pass that also prunes the sums), an OcTree of
// clamped log-odds, and provenance.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <sstream>
#include <thread>

#include "leaf_mapper.hpp"
#include "mapmerge/map/global_delta.hpp"
#include "mapmerge/map/global_fusion.hpp"
#include "mapmerge/map/map_io.hpp"
#include "parallel.hpp"
#include "sum_tree.hpp"
#include "tree_writer.hpp"

namespace mapmerge {
namespace {

/// What a subtree of the global map is once clamped: one state throughout, or mixed.
enum class State : std::uint8_t { kUnknown = 0, kFree = 1, kOccupied = 2, kMixed = 3 };

State leaf_state(std::int64_t packed) {
  if (packed == 0) return State::kUnknown;
  return detail::unpack_sum(packed) >= 0.0 ? State::kOccupied : State::kFree;
}

/// The deepest node of `sums` on the way from `root` to block `id`, at most at block depth, with
/// its key and depth; nullptr when the way ends in a missing child (unknown space). Const or not
/// as `sums` is.
template <class Tree, class Node>
Node* descend_to_block(Tree& sums, Node* root, std::uint64_t id, octomap::OcTreeKey& key,
                       unsigned& depth) {
  const octomap::OcTreeKey target = patch_block_key(id);
  Node* node = root;
  key = octomap::OcTreeKey(32768, 32768, 32768);
  for (depth = 0; node != nullptr && depth < kPatchBlockDepth && sums.nodeHasChildren(node); ++depth) {
    const unsigned i = octomap::computeChildIdx(target, static_cast<int>(15 - depth));
    if (!sums.nodeChildExists(node, i)) return nullptr;
    octomap::computeChildKey(i, static_cast<octomap::key_type>(32768 >> (depth + 1)), key, key);
    node = sums.getNodeChild(node, i);
  }
  return node;
}

/// Writes OcTree::writeBinaryData's body of the maximum-likelihood, pruned global map: per inner
/// node 2 bytes of 2-bit child codes (00 unknown, 01 free, 10 occupied, 11 inner), pre-order.
/// A node's record is reserved before its children are written and dropped again when they all
/// turn out to share one state (the node is then a leaf of its parent). Empty subtrees of the
/// sums are deleted and equal blocks merged on the way. A subtree's bytes depend only on the
/// states of its voxels, so a block (SumTree::kBlockDepth) whose sums did not change since the
/// last run is copied from that run's bytes.
class BodyWriter {
 public:
  BodyWriter(detail::SumTree& sums, detail::EncodedBlocks& last, std::vector<std::uint8_t>& out)
      : sums_(sums), last_(last), out_(out) {}

  /// Writes the body; `changed` lists the blocks whose sums changed (if known), which are written
  /// on several threads first when there are enough of them.
  std::size_t run(const std::optional<std::vector<std::uint64_t>>& changed, unsigned threads = 1) {
    sums_.forget_path();
    detail::SumNode* root = sums_.root_node();
    if (root != nullptr && changed) write_blocks_at_once(root, *changed, threads);
    State s = State::kUnknown;
    if (root != nullptr) s = write(root, octomap::OcTreeKey(32768, 32768, 32768), 0);
    sums_.account(deleted_);
    last_.blocks.swap(next_);  // blocks no longer in the map are forgotten
    sums_.forget_changes();
    if (root == nullptr) return 0;
    if (s == State::kUnknown) {
      sums_.drop_all();
      sums_.forget_changes();  // nothing was known: the next encoding's changes are its patches
      last_.blocks.clear();
      return 0;
    }
    if (s != State::kMixed) {  // the whole key space in one state: a root with 8 leaves
      const std::uint8_t b = s == State::kFree ? 0x55 : 0xAA;
      out_.push_back(b);
      out_.push_back(b);
      return 9;
    }
    return nodes_ + 1;
  }

 private:
  /// Changed blocks are independent subtrees, each one contiguous run of the body: with at least
  /// kParallelBlocks of them they are written on up to `threads` threads (each with its own buffer and
  /// deletion count), and write() takes their bytes as it would those of unchanged blocks.
  static constexpr std::size_t kParallelBlocks = 8;
  void write_blocks_at_once(detail::SumNode* root, const std::vector<std::uint64_t>& ids, unsigned threads) {
    if (threads < 2 || ids.size() < kParallelBlocks) return;
    struct Job {
      std::uint64_t id;
      detail::SumNode* node;
      octomap::OcTreeKey key;
      detail::EncodedBlock block;
    };
    std::vector<Job> jobs;
    for (const std::uint64_t id : ids) {
      octomap::OcTreeKey key;
      unsigned depth = 0;
      detail::SumNode* node = descend_to_block(sums_, root, id, key, depth);
      // Only inner nodes at block depth: write() handles leaves and missing blocks itself.
      if (node != nullptr && depth == detail::SumTree::kBlockDepth && sums_.nodeHasChildren(node))
        jobs.push_back({id, node, key, {}});
    }
    if (jobs.size() < kParallelBlocks) return;
    std::atomic<std::size_t> next{0};
    std::atomic<std::size_t> deleted{0};
    auto work = [&] {
      std::vector<std::uint8_t> bytes;
      detail::EncodedBlocks none;
      BodyWriter writer(sums_, none, bytes);
      for (std::size_t k = next++; k < jobs.size(); k = next++) {
        bytes.clear();
        writer.nodes_ = 0;
        const State state = writer.write_inner(jobs[k].node, jobs[k].key, detail::SumTree::kBlockDepth);
        jobs[k].block.bytes = bytes;
        jobs[k].block.nodes = writer.nodes_;
        jobs[k].block.state = static_cast<std::uint8_t>(state);
      }
      deleted += writer.deleted_;
    };
    detail::run_parallel(std::min<unsigned>(threads, static_cast<unsigned>(jobs.size() / 4)), work);
    deleted_ += deleted;
    for (Job& job : jobs) written_.emplace(job.id, std::move(job.block));
  }

  State write(detail::SumNode* node, const octomap::OcTreeKey& key, unsigned depth) {
    if (depth == detail::SumTree::kBlockDepth && !written_.empty()) {
      const std::uint64_t id = detail::SumTree::block_of(key);
      if (auto it = written_.find(id); it != written_.end()) {  // by write_blocks_at_once(), maybe pruned since
        out_.insert(out_.end(), it->second.bytes.begin(), it->second.bytes.end());
        nodes_ += it->second.nodes;
        const auto state = static_cast<State>(it->second.state);
        next_[id] = std::move(it->second);
        return state;
      }
    }
    if (!sums_.nodeHasChildren(node)) return leaf_state(node->getValue());
    if (depth != detail::SumTree::kBlockDepth) return write_inner(node, key, depth);
    const std::uint64_t id = detail::SumTree::block_of(key);
    if (!sums_.changed(id)) {
      if (auto it = last_.blocks.find(id); it != last_.blocks.end()) {
        out_.insert(out_.end(), it->second.bytes.begin(), it->second.bytes.end());
        nodes_ += it->second.nodes;
        const auto state = static_cast<State>(it->second.state);
        next_.emplace(id, std::move(it->second));
        return state;
      }
    }
    const std::size_t at = out_.size(), nodes_before = nodes_;
    const State state = write_inner(node, key, depth);
    detail::EncodedBlock& block = next_[id];
    block.bytes.assign(out_.begin() + static_cast<std::ptrdiff_t>(at), out_.end());
    block.state = static_cast<std::uint8_t>(state);
    block.nodes = nodes_ - nodes_before;
    return state;
  }

  State write_inner(detail::SumNode* node, const octomap::OcTreeKey& key, unsigned depth) {
    const std::size_t at = out_.size();
    out_.resize(at + 2, 0);
    State states[8];
    const auto offset = static_cast<octomap::key_type>(32768 >> (depth + 1));
    for (unsigned i = 0; i < 8; ++i) {
      states[i] = State::kUnknown;
      if (!sums_.nodeChildExists(node, i)) continue;
      octomap::OcTreeKey child_key;
      octomap::computeChildKey(i, offset, key, child_key);
      states[i] = write(sums_.getNodeChild(node, i), child_key, depth + 1);  // depth <= 16: bounded recursion
      if (states[i] == State::kUnknown) sums_.drop_child(node, i, deleted_);
    }
    sums_.prune(node, deleted_);  // merges 8 equal leaves; no-op otherwise
    if (states[0] != State::kMixed && std::all_of(states, states + 8, [&](State s) { return s == states[0]; })) {
      out_.resize(at);  // uniform: the parent records it as a leaf
      return states[0];
    }
    for (unsigned i = 0; i < 8; ++i) {
      const auto code = static_cast<unsigned>(states[i]);
      const unsigned bits = code == 1 ? 1U : code == 2 ? 2U : code;  // free 01, occupied 10
      out_[at + i / 4] = static_cast<std::uint8_t>(out_[at + i / 4] | (bits << (2 * (i % 4))));
      nodes_ += states[i] != State::kUnknown;
    }
    return State::kMixed;
  }

  detail::SumTree& sums_;
  detail::EncodedBlocks& last_;
  std::unordered_map<std::uint64_t, detail::EncodedBlock> next_;
  std::unordered_map<std::uint64_t, detail::EncodedBlock> written_;  ///< changed blocks written at once
  std::vector<std::uint8_t>& out_;
  std::size_t nodes_ = 0;
  std::size_t deleted_ = 0;  ///< sum nodes deleted (drop_child, prune), for SumTree::account()
};

std::string bt_header(std::size_t nodes, double resolution) {
  std::ostringstream header;  // default stream formatting, as OctoMap's writer
  header << "# Octomap OcTree binary file\n"
            "# (feel free to add / change comments, but leave the first line as it is!)\n#\n"
         << "id OcTree\n"
         << "size " << nodes << "\n"
         << "res " << resolution << "\n"
         << "data\n";
  return header.str();
}

/// Copies the sums' leaves, clamped, into an OcTree.
void copy_leaves(const detail::SumTree& sums, const detail::SumNode* node, const octomap::OcTreeKey& key,
                 unsigned depth, detail::TreeWriter& writer) {
  if (!sums.nodeHasChildren(node)) {
    if (node->getValue() != 0) {
      writer.add(key, 16 - depth, static_cast<float>(detail::unpack_sum(node->getValue())));
    }
    return;
  }
  const auto offset = static_cast<octomap::key_type>(32768 >> (depth + 1));
  for (unsigned i = 0; i < 8; ++i) {
    if (!sums.nodeChildExists(node, i)) continue;
    octomap::OcTreeKey k;
    octomap::computeChildKey(i, offset, key, k);
    copy_leaves(sums, sums.getNodeChild(node, i), k, depth + 1, writer);
  }
}

/// Provenance's sink: occupied evidence voted for, voxel by voxel.
struct VoteSink {
  Provenance& provenance;
  std::uint16_t robot;
  void apply(const octomap::OcTreeKey& key, unsigned level, float delta) {
    const int n = 1 << level;
    for (int i = 0; i < n * n * n; ++i) {
      provenance.vote(octomap::OcTreeKey(static_cast<octomap::key_type>(key[0] + i % n),
                                         static_cast<octomap::key_type>(key[1] + (i / n) % n),
                                         static_cast<octomap::key_type>(key[2] + i / (n * n))),
                      robot, delta);
    }
  }
};

/// The new content of each block in `ids`, after BodyWriter ran: its bytes as just written, or
/// the state of the uniform region (or unknown space) it lies in. Nullopt when the records would
/// outweigh half of the whole `body` (the receiver then does better to decode the map).
std::optional<std::vector<BlockPatch>> patches_of(const detail::SumTree& sums, const detail::EncodedBlocks& blocks,
                                                  const std::vector<std::uint64_t>& ids, std::size_t body_bytes) {
  std::vector<BlockPatch> patches(ids.size());
  std::size_t bytes = 0;
  for (std::size_t k = 0; k < ids.size(); ++k) {
    BlockPatch& p = patches[k];
    p.block = ids[k];
    if (auto it = blocks.blocks.find(ids[k]); it != blocks.blocks.end()) {
      p.state = static_cast<BlockState>(it->second.state);
      if (p.state == BlockState::kMixed) p.records = it->second.bytes;
      bytes += p.records.size();
      if (bytes > body_bytes / 2) return std::nullopt;
      continue;
    }
    // Not written as a block: a leaf at or above block depth, or nothing (unknown).
    octomap::OcTreeKey key;
    unsigned depth = 0;
    const detail::SumNode* node = descend_to_block(sums, sums.root_node(), ids[k], key, depth);
    if (node != nullptr && sums.nodeHasChildren(node)) return std::nullopt;  // an inner block the writer did not keep: cannot happen
    p.state = node == nullptr ? BlockState::kUnknown : static_cast<BlockState>(leaf_state(node->getValue()));
  }
  return patches;
}

}  // namespace

GlobalFusion::Encoded GlobalFusion::encode() {
  constexpr std::size_t kMaxPatchBlocks = std::size_t{1} << 16;
  Encoded e;
  const auto changed = sums_->changed_blocks(kMaxPatchBlocks);  // before the writer forgets them
  e.nodes = BodyWriter(*sums_, *encoded_, e.body).run(changed, threads_);
  if (changed) e.patches = patches_of(*sums_, *encoded_, *changed, e.body.size());
  const std::string header = bt_header(e.nodes, resolution_);
  e.bt.reserve(header.size() + e.body.size());
  e.bt.assign(header.begin(), header.end());
  e.bt.insert(e.bt.end(), e.body.begin(), e.body.end());
  return e;
}

std::unique_ptr<octomap::OcTree> GlobalFusion::tree() const {
  auto tree = std::make_unique<octomap::OcTree>(resolution_);
  if (const detail::SumNode* root = sums_->root_node()) {
    detail::TreeWriter writer(*tree);
    copy_leaves(*sums_, root, octomap::OcTreeKey(32768, 32768, 32768), 0, writer);
  }
  tree->updateInnerOccupancy();
  tree->prune();
  return tree;
}

Provenance provenance_of(const std::vector<NamedMap>& maps, double resolution) {
  if (!(resolution > 0.0) || !std::isfinite(resolution)) throw MapError("provenance_of: resolution must be positive");
  Provenance p;
  p.resolution = resolution;
  const octomap::OcTree grid(resolution);  // key arithmetic of the global grid
  for (const NamedMap& named : maps) {
    const auto index = static_cast<std::uint16_t>(p.robots.size());
    p.robots.push_back(RobotFrame{named.name, named.T_global_map});
    if (named.map == nullptr || !detail::check_rigid(named.T_global_map, 1e-6).empty()) continue;  // no votes
    VoteSink sink{p, index};
    FuseResult counts;
    detail::LeafMapper<VoteSink, float> mapper(named.T_global_map, resolution, sink, counts);
    for (auto it = named.map->begin_leafs(), end = named.map->end_leafs(); it != end; ++it) {
      const float v = it->getLogOdds();
      if (v <= 0.0F) continue;
      const Eigen::Vector3d c(it.getX(), it.getY(), it.getZ());
      if (it.getSize() >= resolution * (1 - 1e-9)) {
        mapper.add_cube(c, it.getSize(), v);
        continue;
      }
      const Eigen::Vector3d ct = named.T_global_map.topLeftCorner<3, 3>() * c + named.T_global_map.topRightCorner<3, 1>();
      octomap::OcTreeKey key;
      if (grid.coordToKeyChecked(ct.x(), ct.y(), ct.z(), key)) p.vote(key, index, v);
    }
  }
  return p;
}

Provenance GlobalFusion::provenance() const {
  std::vector<NamedMap> maps;
  std::vector<std::shared_ptr<const octomap::OcTree>> trees;  // built here if not yet
  for (const auto& [robot, entry] : robots_) {
    trees.push_back(entry.map->tree());
    maps.push_back(NamedMap{robot, trees.back().get(), entry.pose()});  // a robot moving in steps: its new pose
  }
  return provenance_of(maps, resolution_);
}

}  // namespace mapmerge
