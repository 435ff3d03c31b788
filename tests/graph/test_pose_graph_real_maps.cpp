// PoseGraph on real alignments: five robots cut from one real map (five_robots.hpp, geb079),
// every overlapping pair aligned by the real pipeline (global search, no initial guess; where
// that fails, local refinement from the truth displaced by 0.5 m and 3 deg, as the server
// refines an extra pair from its pose estimates), then
// one alignment deliberately replaced by a wrong one (the corridor turned about the vertical):
// the wrong edge is rejected by the cycle checks and every robot the graph places is within
// tolerance of the truth.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <string>
#include <vector>

#include "five_robots.hpp"
#include "mapmerge/align/align.hpp"
#include "mapmerge/graph/information.hpp"
#include "mapmerge/graph/pose_graph.hpp"

namespace mg = mapmerge::graph;
namespace ma = mapmerge::align;
using mapmerge::test::FiveRobots;

namespace {

constexpr double kRotationTolDeg = 1.0;
constexpr double kTranslationTol = 0.2;  // [m], 2.5 voxels of geb079
constexpr int kReference = 2;            // r3, the middle robot (degree 4)

Eigen::AlignedBox3d box_of(const octomap::OcTree& t) {
  double x0, y0, z0, x1, y1, z1;
  t.getMetricMin(x0, y0, z0);
  t.getMetricMax(x1, y1, z1);
  return Eigen::AlignedBox3d(Eigen::Vector3d(x0, y0, z0), Eigen::Vector3d(x1, y1, z1));
}

struct RealEdge {
  int target = -1, source = -1;
  mg::Edge edge;
  mg::AlignmentQuality quality;
};

/// Every overlapping pair aligned once per process (lower index = target).
const std::vector<RealEdge>& real_edges() {
  static const std::vector<RealEdge> edges = [] {
    const FiveRobots& f = FiveRobots::get();
    const ma::AlignConfig config;
    std::vector<ma::PreparedMap> prepared;
    for (const auto& m : f.maps) prepared.push_back(ma::prepare_map(*m, config));
    std::vector<RealEdge> out;
    for (const auto& [t, s] : f.overlapping) {
      ma::AlignResult r = ma::align(prepared[t], prepared[s], config);
      if (!r.accepted) {
        const Eigen::Matrix4d guess = f.truth(t, s) * mapmerge::paper_transform(0.3, -0.3, 0.2, 1, -1, 3);
        r = ma::refine(prepared[t], prepared[s], guess, config);
      }
      if (!r.accepted) continue;  // the tests check which pairs made it
      RealEdge e;
      e.target = t;
      e.source = s;
      const Eigen::Isometry3d T(r.T_target_source);
      e.quality = {r.inliers, r.fitness, r.overlap,
                   mg::overlap_pivot(box_of(*f.maps[s]), box_of(*f.maps[t]), T)};
      const mg::EdgeInformation info = mg::information_from_alignment(e.quality);
      if (!info.valid) continue;
      e.edge = {f.ids[s], f.ids[t], T, info.information, ""};
      out.push_back(e);
    }
    return out;
  }();
  return edges;
}

double rotation_deg(const Eigen::Matrix3d& R) {
  return std::acos(std::clamp((R.trace() - 1.0) / 2.0, -1.0, 1.0)) * 180.0 / M_PI;
}

/// Every connected robot within tolerance of the truth (T_r3_robot); returns how many.
int expect_connected_within_tolerance(const mg::GraphSolution& s, const std::string& what) {
  const FiveRobots& f = FiveRobots::get();
  int connected = 0;
  for (std::size_t i = 0; i < f.ids.size(); ++i) {
    const mg::RobotSolution* r = s.robot(f.ids[i]);
    if (r == nullptr || !r->connected) continue;
    ++connected;
    const Eigen::Matrix4d truth = f.truth(kReference, i);
    const Eigen::Matrix4d est = r->T_global_robot.matrix();
    EXPECT_LT(rotation_deg(truth.topLeftCorner<3, 3>().transpose() * est.topLeftCorner<3, 3>()), kRotationTolDeg)
        << what << " " << f.ids[i];
    EXPECT_LT((truth.topRightCorner<3, 1>() - est.topRightCorner<3, 1>()).norm(), kTranslationTol)
        << what << " " << f.ids[i];
  }
  return connected;
}

mg::PoseGraph graph_of(const std::vector<RealEdge>& edges) {
  mg::PoseGraph g;
  g.set_reference(FiveRobots::get().ids[kReference]);
  for (const auto& id : FiveRobots::get().ids) g.add_robot(id);
  for (const auto& e : edges) g.add_or_update_edge(e.edge);
  return g;
}

std::map<int, int> degrees(const std::vector<RealEdge>& edges) {
  std::map<int, int> d;
  for (const auto& e : edges) {
    ++d[e.target];
    ++d[e.source];
  }
  return d;
}

/// The alignment turned by angle_deg about the world's vertical at the overlap's pivot.
mg::Edge made_wrong(const RealEdge& e, double angle_deg) {
  const Eigen::Vector3d axis = FiveRobots::get().up(static_cast<std::size_t>(e.source));
  const Eigen::Translation3d to(e.quality.pivot_source), back(-e.quality.pivot_source);
  const Eigen::Isometry3d turn(Eigen::AngleAxisd(angle_deg * M_PI / 180.0, axis));
  mg::Edge wrong = e.edge;
  wrong.T_target_source = e.edge.T_target_source * (to * turn * back);
  return wrong;
}

}  // namespace

TEST(PoseGraphRealMaps, EveryOverlappingPairAlignsAndTheGraphHasLoops) {
  const auto& edges = real_edges();
  EXPECT_EQ(edges.size(), FiveRobots::get().overlapping.size());
  ASSERT_GE(edges.size(), 6u);  // a tree of five robots has 4 edges
  mg::PoseGraph g = graph_of(edges);
  const mg::GraphSolution s = g.optimise({});
  ASSERT_TRUE(s.valid) << s.reason;
  for (const auto& e : s.edges) {
    EXPECT_EQ(e.state, mg::EdgeState::kAccepted) << e.id << ": " << e.reason;
    EXPECT_TRUE(e.verified) << e.id;
  }
  EXPECT_EQ(expect_connected_within_tolerance(s, "real edges"), 5);
}

// Each real edge in turn replaced by a wrong one: it is rejected with its evidence, no robot
// gets a wrong pose, and when both its robots have other loops to check it against, every
// robot stays placed. (One test, not one per edge: the alignments are computed once.)
TEST(PoseGraphRealMaps, AnyOneWrongEdgeIsRejectedAndEveryPoseIsWithinTolerance) {
  const std::vector<RealEdge>& edges = real_edges();
  const auto d = degrees(edges);
  for (std::size_t k = 0; k < edges.size(); ++k) {
    const mg::Edge wrong = made_wrong(edges[k], 100.0 + 10.0 * static_cast<double>(k));
    SCOPED_TRACE("wrong edge " + wrong.target + "|" + wrong.source);
    mg::PoseGraph g = graph_of(edges);
    g.add_or_update_edge(wrong);
    const mg::GraphSolution s = g.optimise({});
    ASSERT_TRUE(s.valid);
    const mg::EdgeSolution* e = s.edge(mg::default_edge_id(wrong.source, wrong.target));
    ASSERT_NE(e, nullptr);
    EXPECT_EQ(e->state, mg::EdgeState::kRejected);
    EXPECT_FALSE(e->reason.empty());
    ASSERT_FALSE(e->evidence.empty());
    EXPECT_FALSE(e->evidence.front().consistent);
    EXPECT_GT(e->evidence.front().rotation_error_deg, 45.0);
    const int connected = expect_connected_within_tolerance(s, "wrong " + e->id);
    if (d.at(edges[k].target) >= 3 && d.at(edges[k].source) >= 3) {
      EXPECT_EQ(connected, 5);
    } else {
      EXPECT_GE(connected, 4);  // at most the robot whose two edges disagree drops out
    }
  }
}

TEST(PoseGraphRealMaps, RobotWhoseOnlyEdgesAreWrongBecomesUnknown) {
  std::vector<RealEdge> edges = real_edges();
  mg::PoseGraph g = graph_of(edges);
  int turned = 0;
  for (const auto& e : edges) {
    if (e.source == 4 || e.target == 4) {  // r5: edges to r3 and r4 only
      g.add_or_update_edge(made_wrong(e, 150.0 - 40.0 * turned++));
    }
  }
  ASSERT_EQ(turned, 2);
  const mg::GraphSolution s = g.optimise({});
  const mg::RobotSolution* r5 = s.robot("r5");
  ASSERT_NE(r5, nullptr);
  EXPECT_FALSE(r5->connected);
  EXPECT_EQ(r5->accepted_edges, 0);
  EXPECT_EQ(expect_connected_within_tolerance(s, "others"), 4);
}
