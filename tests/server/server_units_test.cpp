// The server's units without DDS: admission of updates, global poses from pairwise edges,
// the coalescing scheduler, the SQLite store (reopened as after a crash), the config loader.

#include <sys/resource.h>
#include <unistd.h>

#include <atomic>
#include <condition_variable>
#include <filesystem>
#include <fstream>
#include <limits>
#include <mutex>
#include <thread>

#include <gtest/gtest.h>
#include <sqlite3.h>

#include "child_process.hpp"
#include "five_robots.hpp"
#include "fleet.hpp"
#include "mapmerge/map/crop.hpp"
#include "mapmerge/map/global_fusion.hpp"
#include "mapmerge/map/map_codec.hpp"
#include "mapmerge/map/map_io.hpp"
#include "mapmerge/server/config.hpp"
#include "mapmerge/server/export.hpp"
#include "mapmerge/server/global_map.hpp"
#include "mapmerge/server/merge_ops.hpp"
#include "mapmerge/server/pipeline.hpp"
#include "mapmerge/server/pose_graph.hpp"
#include "mapmerge/server/registry.hpp"
#include "mapmerge/server/scheduler.hpp"
#include "mapmerge/server/store.hpp"

namespace mapmerge::server {
namespace {

using namespace std::chrono_literals;

TEST(Registry, IgnoresDuplicatesAndOutOfOrderAndRestartsWithASession) {
  Registry r;
  EXPECT_EQ(r.admit("r1", "a", 5), Admission::kNew);
  EXPECT_EQ(r.admit("r1", "a", 5), Admission::kDuplicate);
  EXPECT_EQ(r.admit("r1", "a", 4), Admission::kOutOfOrder);
  EXPECT_EQ(r.admit("r1", "a", 6), Admission::kNew);
  EXPECT_EQ(r.admit("r1", "b", 1), Admission::kNewSession);  // rebooted: numbering restarts
  EXPECT_EQ(r.admit("r1", "b", 2), Admission::kNew);
  EXPECT_EQ(r.admit("r2", "a", 1), Admission::kNew);         // robots are independent
}

TEST(Registry, SequenceNumbersCompareAsSerialNumbersAndWrap) {
  Registry r;
  constexpr std::uint64_t kMax = std::numeric_limits<std::uint64_t>::max();
  EXPECT_EQ(r.admit("r1", "a", kMax - 1), Admission::kNew);
  EXPECT_EQ(r.admit("r1", "a", kMax), Admission::kNew);
  EXPECT_EQ(r.admit("r1", "a", 0), Admission::kNew);  // wrapped: 0 follows 2^64 - 1
  EXPECT_EQ(r.admit("r1", "a", 1), Admission::kNew);
  EXPECT_EQ(r.admit("r1", "a", kMax), Admission::kOutOfOrder);  // from before the wrap
  EXPECT_EQ(r.admit("r1", "a", 1), Admission::kDuplicate);
  EXPECT_EQ(r.next_sequence("r1", "a"), 2u);
  EXPECT_EQ(r.admit("r1", "a", 1 + (std::uint64_t{1} << 62)), Admission::kNew);  // a gap, still ahead
  EXPECT_EQ(r.ignored("r1"), 2u);
  EXPECT_EQ(r.ignored("r2"), 0u);
}

TEST(Registry, TwoParticipantsUsingOneRobotIdDoNotTakeTurns) {
  Registry r;
  r.set_conflict_hold(30.0);
  const auto t0 = Registry::Clock::now();
  EXPECT_EQ(r.admit("r1", "a", 1, t0), Admission::kNew);
  EXPECT_EQ(r.admit("r1", "b", 1, t0 + 1s), Admission::kNewSession);  // as far as anyone can tell, a restart
  EXPECT_EQ(r.admit("r1", "a", 2, t0 + 2s), Admission::kConflict);    // but a still publishes
  EXPECT_TRUE(r.first_conflict("r1", "a"));
  EXPECT_FALSE(r.first_conflict("r1", "a"));                           // reported once
  EXPECT_EQ(r.admit("r1", "b", 2, t0 + 3s), Admission::kNew);         // b keeps the id
  EXPECT_EQ(r.admit("r1", "a", 3, t0 + 20s), Admission::kConflict);
  EXPECT_EQ(r.session_of("r1"), "b");
  EXPECT_EQ(r.admit("r1", "b", 2, t0 + 25s), Admission::kDuplicate);   // b republishes: still in force
  EXPECT_EQ(r.admit("r1", "a", 4, t0 + 50s), Admission::kConflict);
  EXPECT_EQ(r.admit("r2", "a", 1, t0 + 20s), Admission::kNew);        // other robots are not affected
  // b has been silent for the hold (it left): a takes the id over, and b is the replaced one now.
  EXPECT_EQ(r.admit("r1", "a", 5, t0 + 56s), Admission::kNewSession);
  EXPECT_EQ(r.admit("r1", "b", 3, t0 + 57s), Admission::kConflict);
  EXPECT_TRUE(r.first_conflict("r1", "b"));
  // A genuinely new session (a restart) is taken at once.
  EXPECT_EQ(r.admit("r1", "c", 1, t0 + 58s), Admission::kNewSession);
  EXPECT_EQ(r.session_of("r1"), "c");
}

TEST(Registry, AnUnchangedMapOfTheSameSessionIsOnlyTouched) {
  Registry r;
  RobotRecord rec;
  rec.robot_id = "r1";
  rec.session_id = "a";
  rec.sequence = 1;
  rec.map = std::make_shared<const HeldMap>(std::make_shared<const octomap::OcTree>(0.1));
  rec.content_hash = 42;
  r.put_map(rec);
  const auto before = r.get("r1");
  ASSERT_TRUE(before);
  EXPECT_TRUE(r.touch_if_unchanged("r1", "a", 2, 42, 10.0));
  const auto after = r.get("r1");
  EXPECT_EQ(after->map_revision, before->map_revision);  // nothing to decode, prepare or search
  EXPECT_EQ(after->sequence, 2u);
  EXPECT_EQ(before->sequence, 1u);                        // readers keep their snapshot
  EXPECT_FALSE(r.touch_if_unchanged("r1", "a", 3, 43, 11.0));  // other content: a real update
  EXPECT_FALSE(r.touch_if_unchanged("r1", "b", 1, 42, 12.0));  // new session: frame may differ
  EXPECT_FALSE(r.touch_if_unchanged("r2", "a", 1, 42, 13.0));  // unknown robot
}

/// Registry of robots r1..r<n> (r1 the reference), each holding a map.
void add_robots(Registry& r, int n) {
  auto tree = std::make_shared<const octomap::OcTree>(0.1);
  for (int i = 1; i <= n; ++i) {
    RobotRecord rec;
    rec.robot_id = "r" + std::to_string(i);
    rec.session_id = "a";
    rec.map = std::make_shared<const HeldMap>(tree);
    r.put_map(rec);
  }
  r.claim_reference("r1");
}

Edge quality_edge(const std::string& target, const std::string& source, const Eigen::Matrix4d& T_target_source) {
  Edge e{target, source, T_target_source, 0.05};
  e.inliers = 2000;
  e.overlap = 0.3;
  return e;
}

TEST(Registry, PosesComeFromThePoseGraphWithQuality) {
  Registry r;
  add_robots(r, 3);
  const Eigen::Matrix4d T12 = mapmerge::paper_transform(2, 1, 0, 0, 0, 30);
  const Eigen::Matrix4d T23 = mapmerge::paper_transform(-1, 3, 0.2, 0, 0, -50);
  r.put_edge(quality_edge("r1", "r2", T12));
  r.put_edge(quality_edge("r2", "r3", T23));
  const auto poses = r.poses();
  ASSERT_EQ(poses.size(), 3u);
  EXPECT_TRUE(poses.at("r3").T_global_robot.isApprox(T12 * T23, 1e-6));
  EXPECT_EQ(poses.at("r3").hops, 2);
  EXPECT_DOUBLE_EQ(poses.at("r1").quality, 1.0);
  EXPECT_GT(poses.at("r2").quality, 0.0);
  EXPECT_LT(poses.at("r3").quality, 1.0);
  EXPECT_TRUE(r.rejected_edges().empty());
}

TEST(Registry, WrongEdgeIsRejectedByCycleConsistency) {
  // Five robots with known frames, every pair aligned; one alignment is wrong by 25 degrees.
  Registry r;
  add_robots(r, 5);
  std::vector<Eigen::Matrix4d> T_global(6, Eigen::Matrix4d::Identity());
  for (int i = 2; i <= 5; ++i) T_global[i] = mapmerge::paper_transform(4.0 * i, 1.0 - i, 0.1 * i, 0, 0, 35.0 * i);
  for (int t = 1; t <= 5; ++t) {
    for (int s = t + 1; s <= 5; ++s) {
      Eigen::Matrix4d T_t_s = rigid_inverse(T_global[t]) * T_global[s];
      if (t == 3 && s == 5) T_t_s = T_t_s * mapmerge::paper_transform(0.5, 0, 0, 0, 0, 25);
      r.put_edge(quality_edge("r" + std::to_string(t), "r" + std::to_string(s), T_t_s));
    }
  }
  const auto poses = r.poses();
  ASSERT_EQ(poses.size(), 5u);
  for (int i = 2; i <= 5; ++i) {
    const Eigen::Matrix4d& T = poses.at("r" + std::to_string(i)).T_global_robot;
    EXPECT_LT((T.topRightCorner<3, 1>() - T_global[i].topRightCorner<3, 1>()).norm(), 0.01) << i;
    EXPECT_LT((T.topLeftCorner<3, 3>() - T_global[i].topLeftCorner<3, 3>()).norm(), 1e-3) << i;
  }
  const auto rejected = r.rejected_edges();
  ASSERT_EQ(rejected.size(), 1u);
  EXPECT_EQ(rejected[0].target, "r3");
  EXPECT_EQ(rejected[0].source, "r5");
  EXPECT_FALSE(rejected[0].reason.empty());
}

/// The alignment turned by angle_deg about `axis` (source frame) at the edge's pivot: the
/// corridor matched the wrong way round.
Edge turned(Edge e, const Eigen::Vector3d& axis, double angle_deg) {
  Eigen::Matrix4d turn = Eigen::Matrix4d::Identity();
  turn.topLeftCorner<3, 3>() = Eigen::AngleAxisd(angle_deg * M_PI / 180.0, axis.normalized()).toRotationMatrix();
  Eigen::Matrix4d to = Eigen::Matrix4d::Identity(), back = Eigen::Matrix4d::Identity();
  to.topRightCorner<3, 1>() = e.pivot_source;
  back.topRightCorner<3, 1>() = -e.pivot_source;
  e.T_target_source = e.T_target_source * to * turn * back;
  return e;
}

// The server's wrapper of the fleet pose graph on real alignments: five robots cut from geb079
// (five_robots.hpp), every overlapping pair aligned by merge_ops (global search; where it fails,
// a refinement from a displaced truth, as for an extra pair), edges made by make_edge.
TEST(Registry, RealFleetAWrongEdgeIsRejectedWithEvidenceAndARobotWithOnlyWrongEdgesIsUnknown) {
  const test::FiveRobots& f = test::FiveRobots::get();
  Registry r;
  const align::AlignConfig config = server_align_defaults();  // as the server aligns
  std::vector<std::shared_ptr<const align::PreparedMap>> prepared;
  for (std::size_t i = 0; i < f.ids.size(); ++i) {
    RobotRecord rec;
    rec.robot_id = f.ids[i];
    rec.session_id = "a";
    rec.map = std::make_shared<const HeldMap>(f.maps[i]);
    rec.content_hash = i + 1;
    r.put_map(rec);
    std::string error;
    prepared.push_back(prepare(*rec.map, config, true, error));
    ASSERT_TRUE(prepared.back()) << error;
  }
  r.claim_reference("r3");
  std::map<std::pair<int, int>, Edge> edges;
  for (const auto& [t, s] : f.overlapping) {
    align::AlignResult res = align_global(*prepared[t], *prepared[s], config);
    if (!res.accepted) {
      res = align_local(*prepared[t], *prepared[s], f.truth(t, s) * mapmerge::paper_transform(0.3, -0.3, 0.2, 1, -1, 3),
                        config);
    }
    ASSERT_TRUE(res.accepted) << f.ids[t] << " <- " << f.ids[s] << ": " << res.reason;
    edges[{t, s}] = make_edge(*r.get(f.ids[t]), *r.get(f.ids[s]), res);
    r.put_edge(edges[{t, s}]);
  }
  const auto within_tolerance = [&](const std::string& what) {
    const auto poses = r.poses();
    for (const auto& [id, pose] : poses) {
      const std::size_t i = static_cast<std::size_t>(id[1] - '1');
      EXPECT_LT(test::rotation_error_deg(f.truth(2, i), pose.T_global_robot), 1.0) << what << " " << id;
      EXPECT_LT(test::translation_error_m(f.truth(2, i), pose.T_global_robot), 0.2) << what << " " << id;
    }
    return poses.size();
  };
  EXPECT_EQ(within_tolerance("real edges"), 5u);
  EXPECT_TRUE(r.rejected_edges().empty());

  // r2 <- r3 matched the corridor the wrong way round: rejected, its loops as evidence, and the
  // five robots still placed (r2 and r3 have other loops).
  r.put_edge(turned(edges[{1, 2}], f.up(2), 120.0));
  auto rejected = r.rejected_edges();
  ASSERT_EQ(rejected.size(), 1u);
  EXPECT_EQ(rejected[0].target, "r2");
  EXPECT_EQ(rejected[0].source, "r3");
  EXPECT_NE(rejected[0].reason.find("cycle consistency"), std::string::npos) << rejected[0].reason;
  EXPECT_NE(rejected[0].evidence.find("loop r2|r3"), std::string::npos) << rejected[0].evidence;
  EXPECT_NE(rejected[0].evidence.find("open by"), std::string::npos) << rejected[0].evidence;
  EXPECT_EQ(within_tolerance("one wrong edge"), 5u);
  EXPECT_EQ(r.status("r2"), RobotStatus::kAligned);

  // Both of r5's edges wrong: r5 goes back to unknown rather than keeping a wrong pose.
  r.put_edge(turned(edges[{2, 4}], f.up(4), 150.0));
  r.put_edge(turned(edges[{3, 4}], f.up(4), 100.0));
  EXPECT_EQ(r.status("r5"), RobotStatus::kUnknown);
  EXPECT_EQ(r.poses().count("r5"), 0u);
  EXPECT_EQ(within_tolerance("r5's edges wrong"), 4u);
  rejected = r.rejected_edges();
  EXPECT_EQ(rejected.size(), 3u);
  // Repaired (r5's map re-aligned): it comes back.
  r.put_edge(edges[{2, 4}]);
  r.put_edge(edges[{3, 4}]);
  EXPECT_EQ(r.status("r5"), RobotStatus::kAligned);
  EXPECT_EQ(within_tolerance("repaired"), 5u);
}

TEST(Registry, NewSessionDropsTheRobotsAlignments) {
  Registry r;
  auto tree = std::make_shared<const octomap::OcTree>(0.1);
  for (const char* id : {"r1", "r2"}) {
    RobotRecord rec;
    rec.robot_id = id;
    rec.session_id = "a";
    rec.map = std::make_shared<const HeldMap>(tree);
    r.put_map(rec);
  }
  r.claim_reference("r1");
  r.put_edge(Edge{"r1", "r2", Eigen::Matrix4d::Identity(), 0.01});
  EXPECT_EQ(r.status("r2"), RobotStatus::kAligned);
  RobotRecord rebooted;
  rebooted.robot_id = "r2";
  rebooted.session_id = "b";
  rebooted.map = std::make_shared<const HeldMap>(tree);
  r.put_map(rebooted);
  EXPECT_EQ(r.status("r2"), RobotStatus::kUnknown);
  EXPECT_TRUE(r.edges().empty());
}

TEST(PoseGraph, ComposesTransformsAlongTheBestPath) {
  const Eigen::Matrix4d T12 = mapmerge::paper_transform(1, 2, 0, 0, 0, 30);
  const Eigen::Matrix4d T23 = mapmerge::paper_transform(-3, 1, 0.5, 2, 0, -60);
  const Eigen::Matrix4d T13_bad = mapmerge::paper_transform(9, 9, 9, 0, 0, 0);
  // r1 <- r2 <- r3 with good edges; a direct r1 <- r3 edge with a poor fitness loses.
  const std::vector<Edge> edges{{"r1", "r2", T12, 0.02}, {"r3", "r2", rigid_inverse(T23), 0.02},
                                {"r1", "r3", T13_bad, 0.5}, {"r4", "r5", T12, 0.01}};
  const auto poses = global_poses("r1", edges);
  ASSERT_EQ(poses.size(), 3u);  // r4, r5 are not connected to the reference
  EXPECT_TRUE(poses.at("r1").T_global_robot.isIdentity());
  EXPECT_TRUE(poses.at("r2").T_global_robot.isApprox(T12, 1e-12));
  EXPECT_TRUE(poses.at("r3").T_global_robot.isApprox(T12 * T23, 1e-12));
  EXPECT_EQ(poses.at("r3").hops, 2);
}

/// Sets `flag` under `m` and wakes every job waiting for it on `cv`.
void open_gate(std::mutex& m, std::condition_variable& cv, bool& flag) {
  {
    std::lock_guard<std::mutex> lock(m);
    flag = true;
  }
  cv.notify_all();
}

/// Waits up to 30 s for `s` to have nothing queued or running.
bool wait_until_idle(const Scheduler& s) {
  const auto deadline = std::chrono::steady_clock::now() + 30s;
  while (!s.idle() && std::chrono::steady_clock::now() < deadline) std::this_thread::sleep_for(10ms);
  return s.idle();
}

TEST(Scheduler, CoalescesAFastPublisherAndNeverRunsARobotTwiceAtOnce) {
  std::mutex m;
  std::condition_variable cv;
  bool release = false;
  std::atomic<int> running{0}, max_running{0};
  std::vector<std::uint64_t> processed;
  Scheduler s(4, [&](const std::string&, std::optional<MapSample> map, bool) {
    const int now = ++running;
    max_running = std::max(max_running.load(), now);
    std::unique_lock<std::mutex> lock(m);
    cv.wait(lock, [&] { return release; });
    if (map) processed.push_back(map->sequence);
    --running;
  });
  for (std::uint64_t seq = 1; seq <= 50; ++seq) {
    MapSample sample;
    sample.robot_id = "r1";
    sample.sequence = seq;
    s.submit(sample);
  }
  open_gate(m, cv, release);
  ASSERT_TRUE(wait_until_idle(s));
  const SchedulerStats st = s.stats();
  EXPECT_EQ(max_running.load(), 1);           // one robot: one job at a time
  EXPECT_LE(processed.size(), 2u);            // the first (already running) and the latest
  EXPECT_EQ(processed.back(), 50u);           // latest wins
  EXPECT_EQ(st.coalesced + processed.size(), 50u);
  EXPECT_LE(st.max_queued, 1u);               // the queue holds robots, not updates
}

TEST(Scheduler, AWaitingMapGoesBeforeRetriesButARetryWaitsAtMostFourTurns) {
  std::mutex m;
  std::condition_variable cv;
  bool release = false, started = false;
  std::vector<std::string> order;
  Scheduler s(1, [&](const std::string& robot, std::optional<MapSample> map, bool retry) {
    std::unique_lock<std::mutex> lock(m);
    started = true;
    cv.notify_all();
    cv.wait(lock, [&] { return release; });
    if (robot != "busy") order.push_back(robot + (map ? "+map" : "") + (retry ? "+retry" : ""));
  });
  auto map_of = [](const std::string& robot) {
    MapSample sample;
    sample.robot_id = robot;
    return sample;
  };
  s.submit(map_of("busy"));  // holds the only thread while the queue fills
  {
    std::unique_lock<std::mutex> lock(m);
    ASSERT_TRUE(cv.wait_for(lock, 10s, [&] { return started; }));
  }
  s.retry("search");  // e.g. a global search or a refinement: no new map
  for (int i = 1; i <= 6; ++i) s.submit(map_of("m" + std::to_string(i)));
  open_gate(m, cv, release);
  ASSERT_TRUE(wait_until_idle(s));
  const std::vector<std::string> expected{"m1+map", "m2+map", "m3+map", "m4+map",
                                          "search+retry", "m5+map", "m6+map"};
  EXPECT_EQ(order, expected);
}

TEST(Scheduler, IdleWorkRunsOnSpareThreadsAndNeverStarvesARobot) {
  std::mutex m;
  std::condition_variable cv;
  bool robot_done = false;
  int idle_running = 0, idle_max = 0, handed_out = 0;
  bool robot_ran_during_idle = false;
  Scheduler s(
      2,
      [&](const std::string&, std::optional<MapSample>, bool) {
        std::lock_guard<std::mutex> lock(m);
        robot_ran_during_idle = idle_running > 0;
        robot_done = true;
        cv.notify_all();
      },
      [&]() -> std::function<void()> {
        std::lock_guard<std::mutex> lock(m);
        if (handed_out == 3) return {};
        ++handed_out;
        return [&] {
          std::unique_lock<std::mutex> hold(m);
          idle_max = std::max(idle_max, ++idle_running);
          cv.notify_all();
          cv.wait_for(hold, 20s, [&] { return robot_done; });  // holds a thread until the robot ran
          --idle_running;
        };
      });
  s.kick_idle();
  {
    std::unique_lock<std::mutex> lock(m);
    ASSERT_TRUE(cv.wait_for(lock, 10s, [&] { return idle_running == 1; }));
  }
  EXPECT_EQ(s.stats().running, 1u);  // an idle job counts as running work (status: merges_running)
  EXPECT_EQ(s.stats().queued, 0u);
  MapSample sample;
  sample.robot_id = "r1";
  s.submit(sample);  // must run on the other thread while the idle job holds its own
  ASSERT_TRUE(wait_until_idle(s));
  EXPECT_TRUE(robot_ran_during_idle);
  EXPECT_EQ(idle_max, 1);  // two threads: at most one idle job at a time
  EXPECT_EQ(s.stats().idle_jobs_run, 3u);  // asked again after each job until none is left
  EXPECT_EQ(s.stats().jobs_run, 1u);
  EXPECT_EQ(s.stats().running, 0u);
}

int this_threads_nice() { return getpriority(PRIO_PROCESS, static_cast<id_t>(gettid())); }

TEST(Scheduler, MapsRunBesideBackgroundJobsWhichRunOnTheirOwnLowerPriorityThreads) {
  std::mutex m;
  std::condition_variable cv;
  bool release = false;
  int refine_runs = 0, map_nice = -100, background_nice = -100;
  std::vector<std::string> order;
  Scheduler s(
      1,
      [&](const std::string& key, std::optional<MapSample> map, bool retry) {
        std::unique_lock<std::mutex> lock(m);
        if (map) {
          map_nice = this_threads_nice();
          order.push_back(key + "+map");
          cv.notify_all();
          return;
        }
        EXPECT_TRUE(retry);
        background_nice = this_threads_nice();
        if (key == "r1#refine") ++refine_runs;
        order.push_back(key);
        cv.notify_all();
        cv.wait(lock, [&] { return release; });  // holds the only background thread
      },
      nullptr, 0, Scheduler::Lanes{1, 5});
  s.background("r1#refine");
  {
    std::unique_lock<std::mutex> lock(m);
    ASSERT_TRUE(cv.wait_for(lock, 10s, [&] { return !order.empty(); }));
  }
  for (int i = 0; i < 3; ++i) s.background("r1#refine");  // coalesced into one more run
  s.background("r2#search");
  MapSample sample;
  sample.robot_id = "r1";
  s.submit(sample);  // runs at once on the robots' thread, beside the background job
  {
    std::unique_lock<std::mutex> lock(m);
    ASSERT_TRUE(cv.wait_for(lock, 10s, [&] { return order.size() == 2; }));
    EXPECT_EQ(order.back(), "r1+map");
  }
  open_gate(m, cv, release);
  ASSERT_TRUE(wait_until_idle(s));
  EXPECT_EQ(refine_runs, 2);
  ASSERT_EQ(order.size(), 4u);
  EXPECT_EQ(order[2], "r2#search");  // background jobs in the order asked
  EXPECT_EQ(order[3], "r1#refine");
  EXPECT_EQ(background_nice, std::min(19, map_nice + 5));  // the map's thread keeps the process's priority
  EXPECT_EQ(map_nice, getpriority(PRIO_PROCESS, 0));
}

/// A store in a fresh directory of its own.
StoreConfig fresh_store(const std::string& name) {
  StoreConfig cfg;
  cfg.state_dir = test::temp_dir(name);
  return cfg;
}

/// Robot r1's map update `sequence` of session "s" holding `data`.
MapSample r1_map(std::uint64_t sequence, std::vector<std::uint8_t> data) {
  MapSample m;
  m.robot_id = m.topic_robot = "r1";
  m.session_id = "s";
  m.sequence = sequence;
  m.encoding = "octomap-bt";
  m.data = std::move(data);
  return m;
}

TEST(Store, SurvivesReopeningAndKeepsTheLastOfEverything) {
  const StoreConfig cfg = fresh_store("store_unit");
  MapSample m = r1_map(7, {1, 2, 3});
  GlobalMapOut g;
  g.version = 12;
  g.data = {9, 9};
  g.contributors = {{"r1", "s", 7}};
  const Eigen::Matrix4d T = mapmerge::paper_transform(1, 2, 3, 10, 20, 30);
  {
    Store s(cfg);
    s.save_map(m);
    m.sequence = 8;
    s.save_map(m);
    s.save_alignment("r1", {Edge{"r1", "r2", T, 0.03}});
    s.save_global(g, {PoseOut{"r2", "r2/map", T, 0.03, 0.5, PoseState::kAligned}});
  }
  Store s(cfg);
  const StoreSnapshot snap = s.load();
  EXPECT_EQ(snap.reference, "r1");
  ASSERT_EQ(snap.maps.size(), 1u);
  EXPECT_EQ(snap.maps[0].sequence, 8u);
  EXPECT_EQ(snap.maps[0].data, m.data);
  ASSERT_EQ(snap.edges.size(), 1u);
  EXPECT_TRUE(snap.edges[0].T_target_source.isApprox(T, 0.0));
  ASSERT_TRUE(snap.global.has_value());
  EXPECT_EQ(snap.global->version, 12u);
  EXPECT_EQ(snap.global->contributors.at(0).sequence, 7u);
  ASSERT_EQ(snap.poses.size(), 1u);
  EXPECT_EQ(snap.poses[0].state, PoseState::kAligned);
}

TEST(Store, CheckpointsCopyTheLogIntoTheDatabaseAndLoseNothing) {
  // The store checkpoints on request (the server's main loop), not after each commit: the log
  // holds the writes until then, a checkpoint copies all of them, and a store reopened either
  // way holds the last of everything.
  const StoreConfig cfg = fresh_store("store_checkpoint");
  MapSample m = r1_map(0, std::vector<std::uint8_t>(300'000, 7));  // ~75 pages: SQLite's default would have checkpointed
  {
    Store s(cfg);
    for (std::uint64_t seq = 1; seq <= 30; ++seq) {
      m.sequence = seq;
      ASSERT_TRUE(s.save_map(m));
    }
    const std::uintmax_t wal = std::filesystem::file_size(std::filesystem::path(cfg.state_dir) / "state.sqlite-wal");
    EXPECT_GT(wal, 30u * 300'000u) << "no checkpoint ran after a commit";
    const Store::Checkpoint c = s.checkpoint();
    ASSERT_TRUE(c.ok);
    EXPECT_GT(c.wal_frames, 30u * 70u);
    EXPECT_EQ(c.checkpointed_frames, c.wal_frames);
    m.sequence = 31;
    ASSERT_TRUE(s.save_map(m));  // after the checkpoint, in the log only
  }
  Store s(cfg);
  const StoreSnapshot snap = s.load();
  ASSERT_EQ(snap.maps.size(), 1u);
  EXPECT_EQ(snap.maps[0].sequence, 31u);
  EXPECT_EQ(snap.maps[0].data, m.data);
}

TEST(Store, AGlobalMapsRosBodyIsRestoredFromItsPayload) {
  // The ROS 2 body of a `.bt` global map is its payload without the header: stored once.
  const StoreConfig cfg = fresh_store("store_ros_body");
  GlobalFusion fusion(0.05);
  auto tree = std::make_shared<octomap::OcTree>(0.05);
  for (int i = 0; i < 200; ++i) tree->updateNode(octomap::point3d(0.05f * i, 0.1f, 0.2f), i % 3 != 0);
  ASSERT_TRUE(fusion.set("r1", tree, Eigen::Matrix4d::Identity()).ok);
  GlobalFusion::Encoded e = fusion.encode();
  ASSERT_FALSE(e.body.empty());
  GlobalMapOut g;
  g.version = 3;
  g.encoding = "octomap-bt";
  g.data = e.bt;
  g.ros_body = e.body;
  GlobalMapOut zstd = g;  // another encoding: its body is stored as it is
  zstd.encoding = "octomap-bt+zstd";
  zstd.data = encode_map(*fusion.tree(), Encoding::kOctomapBtZstd);
  for (const GlobalMapOut& out : {g, zstd}) {
    {
      Store s(cfg);
      ASSERT_TRUE(s.save_global(out, {}));
    }
    Store s(cfg);
    const StoreSnapshot snap = s.load();
    ASSERT_TRUE(snap.global.has_value());
    EXPECT_EQ(snap.global->data, out.data) << out.encoding;
    EXPECT_EQ(snap.global->ros_body, out.ros_body) << out.encoding;
  }
}

TEST(Store, EdgesKeepTheirQualityVerdictAndTheirTries) {
  const StoreConfig cfg = fresh_store("store_edges");
  Edge e = quality_edge("r1", "r2", mapmerge::paper_transform(1, 2, 3, 10, 20, 30));
  e.pivot_source = Eigen::Vector3d(0.5, -1.5, 0.25);
  for (int i = 0; i < 6; ++i) e.information(i, i) = 100.0 * (i + 1);
  e.information(0, 4) = e.information(4, 0) = 3.5;
  const EdgeVerdict v{"r1", "r2", "rejected", "cycle consistency: ...", "loop r1|r2 > r2|r3 > r3|r1 open by 90 deg"};
  const PairAttempt tried{"r2", "r3", "extra", 0xFFFFFFFFFFFFFFF0ULL, 42, false, "no hypothesis", 1.5e9};
  {
    Store s(cfg);
    s.save_alignment("r1", {e}, {v});
    s.save_attempt(tried);
    s.save_attempt(PairAttempt{"r2", "r3", "search", 1, 2, true, "", 1.6e9});  // another kind: kept apart
  }
  const StoreSnapshot snap = Store(cfg).load();
  ASSERT_EQ(snap.edges.size(), 1u);
  const Edge& got = snap.edges[0];
  EXPECT_TRUE(got.T_target_source == e.T_target_source);
  EXPECT_EQ(got.inliers, e.inliers);
  EXPECT_EQ(got.overlap, e.overlap);
  EXPECT_EQ(got.fitness, e.fitness);
  EXPECT_TRUE(got.pivot_source == e.pivot_source);
  EXPECT_TRUE(got.information == e.information);
  ASSERT_EQ(snap.verdicts.size(), 1u);
  EXPECT_EQ(snap.verdicts[0].state, "rejected");
  EXPECT_EQ(snap.verdicts[0].reason, v.reason);
  EXPECT_EQ(snap.verdicts[0].evidence, v.evidence);
  ASSERT_EQ(snap.attempts.size(), 2u);
  const PairAttempt& a = snap.attempts[0].kind == "extra" ? snap.attempts[0] : snap.attempts[1];
  EXPECT_EQ(a.hash_a, tried.hash_a);  // 64-bit hashes survive the signed column
  EXPECT_EQ(a.hash_b, 42u);
  EXPECT_FALSE(a.accepted);
  EXPECT_EQ(a.reason, "no hypothesis");
}

TEST(Store, AStoreOfTheFirstSchemaIsUpgradedAndItsEdgesKept) {
  const StoreConfig cfg = fresh_store("store_old_schema");
  const Eigen::Matrix4d T = mapmerge::paper_transform(1, 2, 3, 10, 20, 30);
  {
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open((cfg.state_dir + "/state.sqlite").c_str(), &db), SQLITE_OK);
    ASSERT_EQ(sqlite3_exec(db,
                           "CREATE TABLE edges(target TEXT, source TEXT, T BLOB NOT NULL, fitness REAL, "
                           "PRIMARY KEY(target, source));",
                           nullptr, nullptr, nullptr),
              SQLITE_OK);
    sqlite3_stmt* st = nullptr;
    sqlite3_prepare_v2(db, "INSERT INTO edges VALUES('r1','r2',?,0.03)", -1, &st, nullptr);
    sqlite3_bind_blob(st, 1, T.data(), 16 * sizeof(double), SQLITE_TRANSIENT);
    ASSERT_EQ(sqlite3_step(st), SQLITE_DONE);
    sqlite3_finalize(st);
    sqlite3_close(db);
  }
  const StoreSnapshot snap = Store(cfg).load();
  ASSERT_EQ(snap.edges.size(), 1u);
  EXPECT_TRUE(snap.edges[0].T_target_source == T);
  EXPECT_EQ(snap.edges[0].inliers, 0u);                 // unknown: the registry's typical-edge fallback
  EXPECT_TRUE(snap.edges[0].information.isZero(0.0));
  Registry r;
  add_robots(r, 2);
  r.put_edge(snap.edges[0]);
  EXPECT_EQ(r.status("r2"), RobotStatus::kAligned);
  Store(cfg).save_alignment("r1", snap.edges);  // writes the new columns
  EXPECT_EQ(Store(cfg).load().edges.size(), 1u);
}

TEST(Store, UnwritableDirectoryIsAClearError) {
  StoreConfig cfg;
  cfg.state_dir = "/proc/mapmerge-cannot-exist";
  EXPECT_THROW(Store s(cfg), StoreError);
}

TEST(Config, ReadsSectionsAndRejectsUnknownKeys) {
  const ServerConfig c = parse_server_config(
      "network: {domain: 7, profile: default}\nmerge: {threads: 3, reference: r9}\n"
      "publish: {min_interval_s: 0.5}\nalign: {validate: {max_fitness: 0.7}}\n");
  EXPECT_EQ(c.network.domain, 7);
  EXPECT_EQ(c.merge.threads, 3);
  EXPECT_EQ(c.merge.reference, "r9");
  EXPECT_DOUBLE_EQ(c.publish.min_interval_s, 0.5);
  EXPECT_DOUBLE_EQ(c.align.validate.max_fitness, 0.7);
  // The align section keeps core/align's defaults but for the rescue, off unless the file sets it.
  EXPECT_FALSE(c.align.rescue.enabled);
  EXPECT_FALSE(parse_server_config("").align.rescue.enabled);
  EXPECT_FALSE(ServerConfig{}.align.rescue.enabled);
  EXPECT_TRUE(align::AlignConfig{}.rescue.enabled);
  EXPECT_TRUE(parse_server_config("align: {rescue: {enabled: true}}\n").align.rescue.enabled);
  EXPECT_DOUBLE_EQ(parse_server_config("align: {rescue: {non_max_radius: 3}}\n").align.rescue.non_max_radius, 3.0);
  EXPECT_THROW(parse_server_config("merge: {thread: 3}\n"), align::ConfigError);
  EXPECT_THROW(parse_server_config("network: {domain: 200}\n"), align::ConfigError);
  EXPECT_THROW(parse_server_config("merge: {threads: many}\n"), align::ConfigError);
  EXPECT_EQ(parse_server_config("").merge.threads, 2);
  const ServerConfig lanes = parse_server_config("merge: {ingest_threads: 2, merge_nice: 0}\n");
  EXPECT_EQ(lanes.merge.ingest_threads, 2);
  EXPECT_EQ(lanes.merge.merge_nice, 0);
  EXPECT_EQ(parse_server_config("").merge.merge_nice, 10);
  EXPECT_THROW(parse_server_config("merge: {ingest_threads: 0}\n"), align::ConfigError);
  EXPECT_THROW(parse_server_config("merge: {merge_nice: 20}\n"), align::ConfigError);
  EXPECT_EQ(parse_server_config("publish: {move_nodes_per_build: 0}\n").publish.move_nodes_per_build, 0u);
  EXPECT_THROW(parse_server_config("publish: {move_nodes_per_build: -1}\n"), align::ConfigError);
  EXPECT_DOUBLE_EQ(parse_server_config("").merge.alignment_data_hold_s, 30.0);
  EXPECT_DOUBLE_EQ(parse_server_config("merge: {alignment_data_hold_s: 0}\n").merge.alignment_data_hold_s, 0.0);
  EXPECT_THROW(parse_server_config("merge: {alignment_data_hold_s: -1}\n"), align::ConfigError);
}

TEST(Config, ExtraPairSettings) {
  const ServerConfig d = parse_server_config("");
  EXPECT_TRUE(d.merge.idle_rescue);
  EXPECT_DOUBLE_EQ(d.merge.idle_rescue_after_s, 10.0);
  const ServerConfig no_rescue = parse_server_config("merge: {idle_rescue: false, idle_rescue_after_s: 60}\n");
  EXPECT_FALSE(no_rescue.merge.idle_rescue);
  EXPECT_DOUBLE_EQ(no_rescue.merge.idle_rescue_after_s, 60.0);
  EXPECT_THROW(parse_server_config("merge: {idle_rescue_after_s: -1}\n"), align::ConfigError);
  EXPECT_TRUE(d.merge.extra_pairs);
  EXPECT_EQ(d.merge.extra_max_jobs, 0);
  const ServerConfig c = parse_server_config(
      "merge: {extra_pairs: false, extra_min_overlap: 0.25, extra_overlap_samples: 500, extra_global_fallback: false, "
      "extra_max_jobs: 3}\n");
  EXPECT_FALSE(c.merge.extra_pairs);
  EXPECT_DOUBLE_EQ(c.merge.extra_min_overlap, 0.25);
  EXPECT_EQ(c.merge.extra_overlap_samples, 500);
  EXPECT_FALSE(c.merge.extra_global_fallback);
  EXPECT_EQ(c.merge.extra_max_jobs, 3);
  EXPECT_THROW(parse_server_config("merge: {extra_min_overlap: 1.5}\n"), align::ConfigError);
  EXPECT_THROW(parse_server_config("merge: {extra_overlap_samples: 0}\n"), align::ConfigError);
}

TEST(Config, SecuritySettings) {
  const ServerConfig d = parse_server_config("");
  EXPECT_TRUE(d.network.security_keystore.empty());
  EXPECT_EQ(d.network.security_enclave, "mapmerge_server");
  const ServerConfig c = parse_server_config("network: {security_keystore: /etc/keys, security_enclave: base2}\n");
  EXPECT_EQ(c.network.security_keystore, "/etc/keys");
  EXPECT_EQ(c.network.security_enclave, "base2");
  EXPECT_THROW(parse_server_config("network: {security_enclave: \"\"}\n"), align::ConfigError);
}

TEST(Config, LimitsIncludeOccupiedVoxelsAndFusionWork) {
  const ServerConfig c = parse_server_config("limits: {max_occupied_voxels: 1234, max_fusion_work: 2.5e7}\n");
  EXPECT_EQ(c.limits.max_occupied_voxels, 1234u);
  EXPECT_DOUBLE_EQ(c.limits.max_fusion_work, 2.5e7);
  EXPECT_THROW(parse_server_config("limits: {max_fusion_work: 0}\n"), align::ConfigError);
}

std::shared_ptr<const octomap::OcTree> small_tree(double x) {
  auto t = std::make_shared<octomap::OcTree>(0.1);
  for (int i = 0; i < 10; ++i) t->updateNode(octomap::point3d(static_cast<float>(x), 0.1f * i, 0.5f), true);
  return t;
}

std::shared_ptr<const HeldMap> held(std::shared_ptr<const octomap::OcTree> tree) {
  return std::make_shared<const HeldMap>(std::move(tree));
}

TEST(SyncGlobal, OneBadMapIsSkippedAndTheOthersFused) {
  Eigen::Matrix4d not_rigid = Eigen::Matrix4d::Identity();
  not_rigid(0, 0) = 2.0;  // a scale: core refuses it
  const std::vector<PlacedMap> maps{{"r1", held(small_tree(0.0)), Eigen::Matrix4d::Identity()},
                                    {"r2", held(small_tree(1.0)), not_rigid},
                                    {"r3", nullptr, Eigen::Matrix4d::Identity()},
                                    {"r4", held(small_tree(2.0)), Eigen::Matrix4d::Identity()}};
  GlobalFusion fusion(0.1);
  RefusedMaps refused;
  const GlobalSync g = sync_global(fusion, maps, refused);
  EXPECT_EQ(g.fused, (std::vector<std::string>{"r1", "r4"}));
  ASSERT_EQ(g.skipped.size(), 2u);
  EXPECT_EQ(g.skipped[0].first, "r2");
  EXPECT_EQ(g.skipped[1].first, "r3");
  EXPECT_FALSE(g.skipped[0].second.empty());
  const auto tree = fusion.tree();
  const auto* r1 = tree->search(0.05, 0.05, 0.55);
  const auto* r4 = tree->search(2.05, 0.05, 0.55);
  ASSERT_TRUE(r1 && r4);
  EXPECT_TRUE(tree->isNodeOccupied(*r1) && tree->isNodeOccupied(*r4));
  EXPECT_EQ(tree->search(1.05, 0.05, 0.55), nullptr);  // r2 left out
  // The same refused map is not tried again; a robot no longer listed is taken out.
  const GlobalSync again = sync_global(fusion, {maps[0], maps[1]}, refused);
  EXPECT_TRUE(again.skipped.empty());
  EXPECT_EQ(again.fused, std::vector<std::string>{"r1"});
  EXPECT_EQ(fusion.robots(), std::vector<std::string>{"r1"});
}

TEST(SyncGlobal, FusionWorkLimitLeavesNothingFused) {
  FuseConfig tight;
  tight.max_work = 1e-9;
  GlobalFusion fusion(0.1, tight);
  RefusedMaps refused;
  const GlobalSync tiny = sync_global(fusion, {{"r1", held(small_tree(0.0)), Eigen::Matrix4d::Identity()}}, refused);
  EXPECT_TRUE(tiny.fused.empty());
  ASSERT_EQ(tiny.skipped.size(), 1u);
  EXPECT_TRUE(fusion.empty());
}

Eigen::AlignedBox3d box(double x0, double x1) {
  return Eigen::AlignedBox3d(Eigen::Vector3d(x0, -8, -1), Eigen::Vector3d(x1, 8, 4));
}

RobotRecord record_of(const test::RobotMap& robot, std::uint64_t sequence) {
  RobotRecord r;
  r.robot_id = robot.id;
  r.session_id = "s1";
  r.sequence = sequence;
  r.map = std::make_shared<const HeldMap>(robot.tree);
  r.resolution = robot.tree->getResolution();
  return r;
}

/// The record the pipeline makes of `robot`'s map sent as a `.bt` payload (its checked binary
/// body; the tree not built).
RobotRecord received_record_of(const test::RobotMap& robot, std::uint64_t sequence) {
  MapSample s;
  s.robot_id = s.topic_robot = robot.id;
  s.encoding = "octomap-bt";
  s.data = encode_map(*robot.tree, Encoding::kOctomapBt);
  const DecodedMap d = decode_sample(s, DecodeLimits{});
  EXPECT_TRUE(d.map && d.map->binary_body()) << d.reason;
  RobotRecord r = record_of(robot, sequence);
  r.map = d.map;
  return r;
}

/// Two robots along geb079, r2 in a turned frame and aligned to the reference r1, and r2's next,
/// grown map; `make` turns a map into the registry's record (as given, or as received).
struct GrownPair {
  std::shared_ptr<const octomap::OcTree> world = test::load_data_map("geb079.bt");
  Eigen::Matrix4d T2 = mapmerge::paper_transform(-4, 7, 0.3, -3, 2, 155);
  test::RobotMap r1 = test::cut_robot_map(*world, "r1", box(-8, 12), Eigen::Matrix4d::Identity());
  test::RobotMap r2 = test::cut_robot_map(*world, "r2", box(4, 24), T2);
  test::RobotMap r2_grown = test::cut_robot_map(*world, "r2", box(4, 30), T2);

  template <class Make>
  void put_first_maps(Registry& registry, Make make) const {
    registry.claim_reference("r1");
    registry.put_map(make(r1, 1));
    registry.put_map(make(r2, 1));
    registry.put_edge(Edge{"r1", "r2", T2.inverse(), 0.02});
  }
};

TEST(GlobalMapBuilder, AReceivedGrownMapIsDiffedOnItsPayloadBytesAndEqualsAFreshBuild) {
  const GrownPair pair;
  ServerConfig config;
  Registry registry;
  pair.put_first_maps(registry, received_record_of);
  GlobalMapBuilder builder(config);
  ASSERT_TRUE(builder.build(registry, 1));
  const RobotRecord grown = received_record_of(pair.r2_grown, 2);
  ASSERT_FALSE(grown.map->has_tree());
  registry.put_map(grown);
  const auto second = builder.build(registry, 2);
  ASSERT_TRUE(second);
  EXPECT_EQ(builder.last_stages().incremental, 1u);
  EXPECT_EQ(builder.last_stages().from_bodies, 1u);
  EXPECT_FALSE(grown.map->has_tree()) << "a grown map of a known pose was decoded to be fused";
  const auto expected = GlobalMapBuilder(config).build(registry, 2);
  ASSERT_TRUE(expected);
  EXPECT_TRUE(second->data == expected->data) << "the global map diffed on bytes differs from a fresh build";
}

/// `robot`'s map as the pipeline receives it (a `.bt` payload numbered `sequence` of session s1).
MapSample sample_of(const test::RobotMap& robot, std::uint64_t sequence) {
  MapSample s;
  s.robot_id = s.topic_robot = robot.id;
  s.session_id = "s1";
  s.sequence = sequence;
  s.encoding = "octomap-bt";
  s.data = encode_map(*robot.tree, Encoding::kOctomapBt);
  return s;
}

std::size_t refinements(const Pipeline& p) {
  const auto merges = p.recent_merges();
  return static_cast<std::size_t>(
      std::count_if(merges.begin(), merges.end(), [](const MergeReportOut& m) { return !m.global_search; }));
}

TEST(Pipeline, AKnownRobotIsRefinedOnceItsMapChangedByTheConfiguredShare) {
  const GrownPair pair;
  ServerConfig config;  // refine_min_change 0.1
  Registry registry;
  Pipeline pipeline(config, registry, nullptr, {});  // no hooks: refinements run inline
  pipeline.process("r1", sample_of(pair.r1, 1), false);
  pipeline.process("r2", sample_of(pair.r2, 1), false);
  ASSERT_EQ(registry.status("r2"), RobotStatus::kAligned);
  ASSERT_EQ(refinements(pipeline), 0u);
  // A little more of the same corridor: under 10% more nodes keeps the transform, and the map's
  // tree is not even built.
  const test::RobotMap a_bit_more = test::cut_robot_map(*pair.world, "r2", box(4, 24.6), pair.T2);
  const double growth = static_cast<double>(a_bit_more.tree->size()) / pair.r2.tree->size() - 1.0;
  ASSERT_GT(growth, 0.0);
  ASSERT_LT(growth, config.merge.refine_min_change);
  pipeline.process("r2", sample_of(a_bit_more, 2), false);
  EXPECT_EQ(refinements(pipeline), 0u);
  EXPECT_FALSE(registry.get("r2")->map->has_tree());
  // The grown map (a third longer) is refined, from the transform known.
  pipeline.process("r2", sample_of(pair.r2_grown, 3), false);
  EXPECT_EQ(refinements(pipeline), 1u);
  EXPECT_EQ(registry.status("r2"), RobotStatus::kAligned);
  // With 0 every change is refined.
  ServerConfig eager;
  eager.merge.refine_min_change = 0.0;
  Registry registry_eager;
  Pipeline every_change(eager, registry_eager, nullptr, {});
  every_change.process("r1", sample_of(pair.r1, 1), false);
  every_change.process("r2", sample_of(pair.r2, 1), false);
  ASSERT_EQ(registry_eager.status("r2"), RobotStatus::kAligned);
  every_change.process("r2", sample_of(a_bit_more, 2), false);
  EXPECT_EQ(refinements(every_change), 1u);
}

TEST(Pipeline, AlignmentDataNoAlignmentUsesIsLetGoOfAndBuiltAgainWhenNeeded) {
  const GrownPair pair;
  ServerConfig config;
  config.merge.alignment_data_hold_s = 0.0;  // idle at once
  Registry registry;
  Pipeline pipeline(config, registry, nullptr, {});
  pipeline.process("r1", sample_of(pair.r1, 1), false);
  pipeline.process("r2", sample_of(pair.r2, 1), false);
  ASSERT_EQ(registry.status("r2"), RobotStatus::kAligned);
  for (const char* id : {"r1", "r2"}) {
    ASSERT_TRUE(registry.get(id)->prepared) << id;
    // The octree is built from the bytes while the map is prepared, and let go of at once.
    EXPECT_FALSE(registry.get(id)->map->has_tree()) << id;
  }
  GlobalMapBuilder builder(config);
  const auto first = builder.build(registry, 1);
  ASSERT_TRUE(first);
  const auto map2 = registry.get("r2")->map;
  const std::weak_ptr<const align::PreparedMap> prepared2 = registry.get("r2")->prepared;
  const auto running = registry.get("r1")->prepared;  // an alignment still using r1's
  ASSERT_TRUE(pipeline.alignment_data_idle());
  pipeline.process(Pipeline::release_job(), std::nullopt, true);
  for (const char* id : {"r1", "r2"}) EXPECT_FALSE(registry.get(id)->prepared) << id;
  EXPECT_TRUE(prepared2.expired()) << "r2's prepared map is still held";
  EXPECT_GT(running->num_points(), 0u) << "a running alignment lost its prepared map";
  EXPECT_FALSE(pipeline.alignment_data_idle());
  // The maps are the same maps: nothing to fuse again, no new version.
  EXPECT_EQ(registry.get("r2")->map, map2);
  EXPECT_FALSE(builder.build(registry, 2));
  EXPECT_TRUE(builder.unchanged());
  // A grown map is refined against r1's clouds, prepared again from r1's bytes.
  pipeline.process("r2", sample_of(pair.r2_grown, 2), false);
  EXPECT_EQ(refinements(pipeline), 1u);
  EXPECT_EQ(registry.status("r2"), RobotStatus::kAligned);
  EXPECT_TRUE(registry.get("r1")->prepared);
  EXPECT_FALSE(registry.get("r1")->map->has_tree());
  // Data an alignment used since the cutoff is kept.
  registry.note_alignment_use("r1", Registry::Clock::now() + std::chrono::hours(1));
  const auto released = registry.release_alignment_data(Registry::Clock::now());
  EXPECT_EQ(released, std::vector<std::string>{"r2"});
  EXPECT_TRUE(registry.get("r1")->prepared);
  EXPECT_FALSE(registry.get("r2")->prepared);
  // Data an alignment is running on is kept however long ago it began (a search on a loaded
  // machine outlasts the hold), and is idle only from the alignment's end.
  const auto later = Registry::Clock::now() + std::chrono::hours(2);
  {
    const Registry::AlignmentUse running_on_r1(registry, "r1");
    EXPECT_TRUE(registry.release_alignment_data(later).empty());
    EXPECT_TRUE(registry.get("r1")->prepared);
  }
  EXPECT_EQ(registry.release_alignment_data(later), std::vector<std::string>{"r1"});
  EXPECT_FALSE(registry.get("r1")->prepared);
}

TEST(Pipeline, ARobotItsSearchRefusedIsRescuedOnSpareCapacityOncePerPairOfMaps) {
  // fr_078_tidyup cut as the align bench cuts it at 10 % overlap, r2 moved by the transform of
  // AlignPipeline.ANarrowOverlapTheFirstSearchMissesIsFoundOnDenserFeatures: the server's search
  // (whole map, then block by block; no rescue) refuses r2, the idle rescue places it.
  const auto room = test::load_data_map("fr_078_tidyup.bt");
  const auto [first_box, second_box] = mapmerge::overlap_cut(*room, 0, 0.10);
  const Eigen::Matrix4d T2 =
      mapmerge::paper_transform(4.3912779496526042, 2.7838923553891979, 0.21597051103616705, 3.0275750345742836,
                                -4.0719918969240405, 6.5349174219267923);
  const test::RobotMap r1 = test::cut_robot_map(*room, "r1", first_box, Eigen::Matrix4d::Identity());
  const test::RobotMap r2 = test::cut_robot_map(*room, "r2", second_box, T2);
  // r3: a stretch of another building's corridor (fr_079), refused by the search and the rescue.
  const test::RobotMap r3 =
      test::cut_robot_map(*test::load_data_map("fr_079.bt"), "r3", box(-8, -2), Eigen::Matrix4d::Identity());
  ServerConfig config;
  ASSERT_TRUE(config.merge.idle_rescue);
  ASSERT_FALSE(config.align.rescue.enabled);
  Registry registry;
  int kicks = 0;
  std::atomic<bool> stopping{false};
  Pipeline::Hooks hooks;
  hooks.more_idle_work = [&] { ++kicks; };
  hooks.cancelled = [&] { return stopping.load(); };
  Pipeline pipeline(config, registry, nullptr, hooks);  // searches run inline
  pipeline.process("r1", sample_of(r1, 1), false);
  EXPECT_FALSE(pipeline.next_rescue()) << "nothing was refused yet";
  pipeline.process("r2", sample_of(r2, 1), false);
  ASSERT_EQ(registry.status("r2"), RobotStatus::kUnknown) << "the search placed r2: this pair no longer shows the rescue";
  EXPECT_GT(kicks, 0) << "a refused search did not tell the scheduler that idle work may be there";
  // Not while the refusal is recent (r2's map may still grow: a new search comes first).
  ASSERT_GT(config.merge.idle_rescue_after_s, 1.0);
  EXPECT_FALSE(pipeline.next_rescue());
  config.merge.idle_rescue_after_s = 0.0;  // (the pipeline reads the config it was given)

  // A rescue given up midway (the server stops) is neither reported nor remembered.
  std::function<void()> job = pipeline.next_idle_work();
  ASSERT_TRUE(job);
  EXPECT_FALSE(pipeline.next_rescue()) << "a rescue in progress was handed out twice";
  const std::size_t reports = pipeline.recent_merges().size();
  std::thread running(job);
  std::this_thread::sleep_for(300ms);  // the rescue takes seconds
  stopping = true;
  running.join();
  EXPECT_EQ(registry.status("r2"), RobotStatus::kUnknown);
  EXPECT_EQ(pipeline.counters().rescues_tried, 0U);
  EXPECT_EQ(pipeline.recent_merges().size(), reports);
  stopping = false;

  job = pipeline.next_idle_work();
  ASSERT_TRUE(job) << "a rescue given up was remembered as tried";
  job();
  ASSERT_EQ(registry.status("r2"), RobotStatus::kAligned) << pipeline.recent_merges().back().detail;
  const Eigen::Matrix4d T = registry.poses().at("r2").T_global_robot;  // (poses() is a copy)
  EXPECT_LT(test::rotation_error_deg(T2.inverse(), T), 1.0);
  EXPECT_LT(test::translation_error_m(T2.inverse(), T), 0.1);
  EXPECT_EQ(pipeline.recent_merges().back().detail, "rescue");
  EXPECT_TRUE(pipeline.recent_merges().back().global_search);

  pipeline.process("r3", sample_of(r3, 1), false);
  ASSERT_EQ(registry.status("r3"), RobotStatus::kUnknown);
  // One rescue per aligned partner, the larger map first; each refused, and not tried again
  // while the maps stay the same (the same map republished included).
  for (const char* partner : {"r1", "r2"}) {
    job = pipeline.next_rescue();
    ASSERT_TRUE(job) << partner;
    job();
    const MergeReportOut last = pipeline.recent_merges().back();
    EXPECT_EQ(last.source, "r3");
    EXPECT_FALSE(last.accepted);
    EXPECT_EQ(last.detail.rfind("rescue: ", 0), 0U) << last.detail;
  }
  EXPECT_EQ(registry.status("r3"), RobotStatus::kUnknown);
  EXPECT_FALSE(pipeline.next_rescue());
  pipeline.process("r3", sample_of(r3, 2), false);
  EXPECT_FALSE(pipeline.next_rescue());
  const PipelineCounters c = pipeline.counters();
  EXPECT_EQ(c.rescues_tried, 3U);
  EXPECT_EQ(c.rescues_accepted, 1U);

  // With the rescue in every search there is nothing left to do later.
  ServerConfig eager;
  eager.merge.idle_rescue_after_s = 0.0;
  eager.align.rescue.enabled = true;
  eager.merge.search_blocks_fallback = false;
  Registry registry_eager;
  Pipeline in_search(eager, registry_eager, nullptr, {});
  in_search.process("r1", sample_of(r1, 1), false);
  in_search.process("r3", sample_of(r3, 1), false);
  ASSERT_EQ(registry_eager.status("r3"), RobotStatus::kUnknown);
  EXPECT_FALSE(in_search.next_rescue());
}

TEST(GlobalMapBuilder, AGrownMapIsFusedByItsDifferenceAndEqualsAFreshBuild) {
  const GrownPair pair;
  ServerConfig config;
  Registry registry;
  pair.put_first_maps(registry, record_of);
  GlobalMapBuilder builder(config);
  const auto first = builder.build(registry, 1);
  ASSERT_TRUE(first);
  EXPECT_EQ(first->contributors.size(), 2u);
  EXPECT_EQ(builder.last_stages().updated, 2u);

  registry.put_map(record_of(pair.r2_grown, 2));
  const auto second = builder.build(registry, 2);
  ASSERT_TRUE(second);
  EXPECT_EQ(builder.last_stages().updated, 1u);
  EXPECT_EQ(builder.last_stages().incremental, 1u);
  EXPECT_GT(second->data.size(), first->data.size());
  GlobalMapBuilder fresh(config);
  const auto expected = fresh.build(registry, 2);
  ASSERT_TRUE(expected);
  EXPECT_TRUE(second->data == expected->data) << "incremental and fresh global maps differ";
  EXPECT_TRUE(second->ros_body == expected->ros_body);
  const Provenance p = builder.provenance();
  ASSERT_EQ(p.robots.size(), 2u);
  EXPECT_EQ(p.robots[1].name, "r2");
  EXPECT_GT(p.owner.size(), 10000u);
}

TEST(GlobalMapBuilder, APoseWobbleMakesNoNewVersionAndTheNextChangedBlocksStartFromTheLastOne) {
  const GrownPair pair;
  ServerConfig config;
  Registry registry;
  pair.put_first_maps(registry, received_record_of);
  GlobalMapBuilder builder(config);
  const auto first = builder.build(registry, 1);
  ASSERT_TRUE(first);
  EXPECT_FALSE(builder.unchanged());
  // A refinement moves r2 by 5 mm: no point of its map moves by half a voxel.
  registry.put_edge(Edge{"r1", "r2", mapmerge::paper_transform(0.005, 0, 0, 0, 0, 0) * pair.T2.inverse(), 0.02});
  EXPECT_FALSE(builder.build(registry, 2));
  EXPECT_TRUE(builder.unchanged());
  registry.put_map(received_record_of(pair.r2_grown, 2));
  const auto second = builder.build(registry, 2);
  ASSERT_TRUE(second);
  EXPECT_FALSE(builder.unchanged());
  ASSERT_TRUE(second->delta);
  EXPECT_EQ(second->delta->base_version, 1u);
  EXPECT_EQ(second->delta->base_hash, first->hash);
  EXPECT_NE(second->hash, first->hash);
}

TEST(GlobalMapBuilder, AGrownMapIsPublishedBeforeAMovedOneIsFusedAgain) {
  const auto world = test::load_data_map("geb079.bt");
  const Eigen::Matrix4d T2 = mapmerge::paper_transform(-4, 7, 0.3, -3, 2, 155);
  const auto r1 = test::cut_robot_map(*world, "r1", box(-8, 12), Eigen::Matrix4d::Identity());
  const auto r1_grown = test::cut_robot_map(*world, "r1", box(-8, 16), Eigen::Matrix4d::Identity());
  const auto r1_grown_again = test::cut_robot_map(*world, "r1", box(-8, 18), Eigen::Matrix4d::Identity());
  const auto r2 = test::cut_robot_map(*world, "r2", box(4, 24), T2);
  const auto r2_grown = test::cut_robot_map(*world, "r2", box(4, 30), T2);
  ServerConfig config;
  Registry registry;
  registry.claim_reference("r1");
  registry.put_map(record_of(r1, 1));
  registry.put_map(record_of(r2, 1));
  registry.put_edge(Edge{"r1", "r2", T2.inverse(), 0.02});
  GlobalMapBuilder builder(config);
  ASSERT_TRUE(builder.build(registry, 1));
  // r1 grows while r2 grows and is moved by 0.3 m: both differences go out first, r2's at its
  // fused pose; r2's move waits for the next build.
  registry.put_map(record_of(r1_grown, 2));
  registry.put_map(record_of(r2_grown, 2));
  registry.put_edge(Edge{"r1", "r2", mapmerge::paper_transform(0.3, 0, 0, 0, 0, 0) * T2.inverse(), 0.02});
  const auto first = builder.build(registry, 2);
  ASSERT_TRUE(first);
  EXPECT_TRUE(builder.deferred());
  EXPECT_EQ(builder.last_stages().updated, 2u);
  EXPECT_EQ(builder.last_stages().incremental, 2u);
  for (const Contribution& c : first->contributors) EXPECT_EQ(c.sequence, 2u) << c.robot_id;
  Registry unmoved;  // the grown maps at the poses fused before
  unmoved.claim_reference("r1");
  unmoved.put_map(record_of(r1_grown, 2));
  unmoved.put_map(record_of(r2_grown, 2));
  unmoved.put_edge(Edge{"r1", "r2", T2.inverse(), 0.02});
  const auto at_fused_poses = GlobalMapBuilder(config).build(unmoved, 2);
  ASSERT_TRUE(at_fused_poses);
  EXPECT_TRUE(first->data == at_fused_poses->data) << "r2's grown map is not fused at its fused pose";
  // r1 grows again before the next build: the move is not held back a second time.
  registry.put_map(record_of(r1_grown_again, 3));
  const auto second = builder.build(registry, 3);
  ASSERT_TRUE(second);
  EXPECT_FALSE(builder.deferred());
  EXPECT_EQ(builder.last_stages().updated, 2u);
  for (const Contribution& c : second->contributors) EXPECT_EQ(c.sequence, c.robot_id == "r1" ? 3u : 2u) << c.robot_id;
  const auto expected = GlobalMapBuilder(config).build(registry, 3);
  ASSERT_TRUE(expected);
  EXPECT_TRUE(second->data == expected->data) << "after the deferred move, the map differs from a fresh build";
}

TEST(GlobalMapBuilder, AMovedRobotsNewMapGoesOutAtItsFusedPoseBeforeItsMove) {
  // A refinement both grows r2's map and moves r2 by 0.3 m: its whole re-fusion would hold its
  // update back, so the first build fuses the new map's difference at the fused pose, the next
  // one the move.
  const auto world = test::load_data_map("geb079.bt");
  const Eigen::Matrix4d T2 = mapmerge::paper_transform(-4, 7, 0.3, -3, 2, 155);
  const auto r1 = test::cut_robot_map(*world, "r1", box(-8, 12), Eigen::Matrix4d::Identity());
  const auto r2 = test::cut_robot_map(*world, "r2", box(4, 24), T2);
  const auto r2_grown = test::cut_robot_map(*world, "r2", box(4, 30), T2);
  // A builder of its own, fed one registry: a fresh build of `second` at r2's pose moved by `move`.
  const auto fresh = [&](const test::RobotMap& second, std::uint64_t sequence, const Eigen::Matrix4d& move,
                         std::uint64_t version) {
    Registry r;
    r.claim_reference("r1");
    r.put_map(record_of(r1, 1));
    r.put_map(record_of(second, sequence));
    r.put_edge(Edge{"r1", "r2", move * T2.inverse(), 0.02});
    return GlobalMapBuilder(ServerConfig{}).build(r, version);
  };
  const Eigen::Matrix4d shift = mapmerge::paper_transform(0.3, 0, 0, 0, 0, 0);
  ServerConfig config;
  GlobalMapBuilder builder(config);
  Registry registry;
  registry.claim_reference("r1");
  registry.put_map(record_of(r1, 1));
  registry.put_map(record_of(r2, 1));
  registry.put_edge(Edge{"r1", "r2", T2.inverse(), 0.02});
  ASSERT_TRUE(builder.build(registry, 1));
  registry.put_map(record_of(r2_grown, 2));
  registry.put_edge(Edge{"r1", "r2", shift * T2.inverse(), 0.02});
  const auto first = builder.build(registry, 2);
  ASSERT_TRUE(first);
  EXPECT_TRUE(builder.deferred());
  EXPECT_EQ(builder.last_stages().updated, 1u);
  EXPECT_EQ(builder.last_stages().incremental, 1u);
  for (const Contribution& c : first->contributors) EXPECT_EQ(c.sequence, c.robot_id == "r2" ? 2u : 1u) << c.robot_id;
  const auto at_fused_pose = fresh(r2_grown, 2, Eigen::Matrix4d::Identity(), 2);
  ASSERT_TRUE(at_fused_pose);
  EXPECT_TRUE(first->data == at_fused_pose->data) << "r2's new map is not fused at its fused pose";
  const auto second = builder.build(registry, 3);
  ASSERT_TRUE(second);
  EXPECT_FALSE(builder.deferred());
  EXPECT_EQ(builder.last_stages().updated, 1u);
  EXPECT_EQ(builder.last_stages().incremental, 0u);
  const auto moved = fresh(r2_grown, 2, shift, 3);
  ASSERT_TRUE(moved);
  EXPECT_TRUE(second->data == moved->data) << "after the deferred move, the map differs from a fresh build";
}

TEST(GlobalMapBuilder, MovedRobotsAreFusedAgainWithinTheBuildsNodeBudgetUntilAllAre) {
  const auto world = test::load_data_map("geb079.bt");
  const Eigen::Matrix4d T2 = mapmerge::paper_transform(-4, 7, 0.3, -3, 2, 155);
  const Eigen::Matrix4d T3 = mapmerge::paper_transform(5, -3, 0.2, 2, -1, -70);
  const Eigen::Matrix4d shift = mapmerge::paper_transform(0.3, 0, 0, 0, 0, 0);
  Registry registry;
  registry.claim_reference("r1");
  registry.put_map(record_of(test::cut_robot_map(*world, "r1", box(-8, 12), Eigen::Matrix4d::Identity()), 1));
  registry.put_map(record_of(test::cut_robot_map(*world, "r2", box(4, 24), T2), 1));
  registry.put_map(record_of(test::cut_robot_map(*world, "r3", box(14, 31), T3), 1));
  const auto place = [&](const Eigen::Matrix4d& moved) {
    registry.put_edge(Edge{"r1", "r2", moved * T2.inverse(), 0.02});
    registry.put_edge(Edge{"r1", "r3", moved * T3.inverse(), 0.02});
  };
  place(Eigen::Matrix4d::Identity());
  for (const std::size_t budget : {std::size_t{1}, std::size_t{0}}) {
    SCOPED_TRACE("budget " + std::to_string(budget));
    ServerConfig config;
    config.publish.move_nodes_per_build = budget;
    place(Eigen::Matrix4d::Identity());
    GlobalMapBuilder builder(config);
    ASSERT_TRUE(builder.build(registry, 1));  // a first fusion: every robot at once
    EXPECT_EQ(builder.last_stages().updated, 3u);
    EXPECT_FALSE(builder.deferred());
    place(shift);  // the pose graph moves r2 and r3 by 0.3 m
    std::optional<GlobalMapOut> last;
    std::vector<std::size_t> updated;
    for (std::uint64_t version = 2; version < 6 && (version == 2 || builder.deferred()); ++version) {
      last = builder.build(registry, version);
      ASSERT_TRUE(last);
      updated.push_back(builder.last_stages().updated);
    }
    // One robot per build over budget (at least one), both at once without one.
    const std::vector<std::size_t> expected_updates = budget == 0 ? std::vector<std::size_t>{2} : std::vector<std::size_t>{1, 1};
    EXPECT_EQ(updated, expected_updates);
    const auto expected = GlobalMapBuilder(config).build(registry, 9);
    ASSERT_TRUE(expected);
    EXPECT_TRUE(last->data == expected->data) << "after the moves, the map differs from a fresh build";
  }
}

TEST(GlobalMapBuilder, AMovedRobotGoesInStepsAndAnotherRobotsUpdateGoesOutInBetween) {
  // The pose graph moves r2 (its map unchanged): the move goes a few leaves a build, every
  // build's map whole, and r1's update, received meanwhile, goes out in the next build, not
  // after the whole move. The last build equals a fresh one.
  const auto world = test::load_data_map("geb079.bt");
  const Eigen::Matrix4d T2 = mapmerge::paper_transform(-4, 7, 0.3, -3, 2, 155);
  const Eigen::Matrix4d shift = mapmerge::paper_transform(0.3, 0, 0, 0, 0, 2);
  const auto r2 = test::cut_robot_map(*world, "r2", box(4, 24), T2);
  ServerConfig config;
  config.publish.move_step_leaves = r2.tree->getNumLeafNodes() / 5;
  ASSERT_GT(config.publish.move_step_leaves, 1000u);
  Registry registry;
  registry.claim_reference("r1");
  registry.put_map(received_record_of(test::cut_robot_map(*world, "r1", box(-8, 10), Eigen::Matrix4d::Identity()), 1));
  registry.put_map(received_record_of(r2, 1));
  registry.put_edge(Edge{"r1", "r2", T2.inverse(), 0.02});
  GlobalMapBuilder builder(config);
  ASSERT_TRUE(builder.build(registry, 1));
  registry.put_edge(Edge{"r1", "r2", shift * T2.inverse(), 0.02});
  std::uint64_t version = 2;
  ASSERT_TRUE(builder.build(registry, version));
  EXPECT_EQ(builder.last_stages().moving, 1u);
  EXPECT_TRUE(builder.deferred()) << "the move's next steps are due";
  registry.put_map(received_record_of(test::cut_robot_map(*world, "r1", box(-8, 14), Eigen::Matrix4d::Identity()), 2));
  const auto with_update = builder.build(registry, ++version);
  ASSERT_TRUE(with_update);
  EXPECT_EQ(builder.last_stages().incremental, 1u) << "r1's update by its difference";
  EXPECT_EQ(builder.last_stages().moving, 1u) << "r2 still halfway";
  const auto r1_in = std::find_if(with_update->contributors.begin(), with_update->contributors.end(),
                                  [](const Contribution& c) { return c.robot_id == "r1"; });
  ASSERT_NE(r1_in, with_update->contributors.end());
  EXPECT_EQ(r1_in->sequence, 2u) << "r1's update waited for r2's move";
  std::optional<GlobalMapOut> last = with_update;
  while (builder.deferred() && version < 20) {
    last = builder.build(registry, ++version);
    ASSERT_TRUE(last);
  }
  EXPECT_FALSE(builder.deferred());
  EXPECT_EQ(builder.last_stages().moving, 0u);
  EXPECT_GE(version, 5u) << "the move took a single step";
  const auto expected = GlobalMapBuilder(config).build(registry, 99);
  ASSERT_TRUE(expected);
  EXPECT_TRUE(last->data == expected->data) << "after the move in steps, the map differs from a fresh build";

  // r2 grows and is moved at once: its content goes out first (at the fused pose), then the move
  // in steps; a map r2 sends halfway goes out in the next build too, and the move goes on with it.
  const auto sequence_of = [](const GlobalMapOut& g, const std::string& id) {
    for (const Contribution& c : g.contributors) {
      if (c.robot_id == id) return c.sequence;
    }
    return std::uint64_t{0};
  };
  registry.put_map(received_record_of(test::cut_robot_map(*world, "r2", box(4, 28), T2), 2));
  registry.put_edge(Edge{"r1", "r2", shift.inverse() * T2.inverse(), 0.02});
  const auto content = builder.build(registry, ++version);
  ASSERT_TRUE(content);
  EXPECT_EQ(sequence_of(*content, "r2"), 2u);
  EXPECT_EQ(builder.last_stages().incremental, 1u);
  EXPECT_EQ(builder.last_stages().moving, 0u) << "the move started with the new map";
  EXPECT_TRUE(builder.deferred());
  ASSERT_TRUE(builder.build(registry, ++version));
  EXPECT_EQ(builder.last_stages().moving, 1u);
  registry.put_map(received_record_of(test::cut_robot_map(*world, "r2", box(4, 31), T2), 3));
  const auto halfway = builder.build(registry, ++version);
  ASSERT_TRUE(halfway);
  EXPECT_EQ(sequence_of(*halfway, "r2"), 3u) << "r2's own update waited for its move";
  EXPECT_EQ(builder.last_stages().incremental, 1u);
  EXPECT_EQ(builder.last_stages().moving, 1u);
  EXPECT_TRUE(builder.deferred()) << "the move goes on";
  // r2 sends a new map for every build: its move still ends (its step goes with its new map,
  // every other build at least).
  last = halfway;
  std::uint64_t sequence = 3;
  int builds = 0;
  for (; builder.last_stages().moving > 0 && builds < 20; ++builds) {
    ++sequence;
    registry.put_map(received_record_of(test::cut_robot_map(*world, "r2", box(4, sequence % 2 == 0 ? 30 : 31), T2),
                                        sequence));
    last = builder.build(registry, ++version);
    ASSERT_TRUE(last);
    EXPECT_EQ(sequence_of(*last, "r2"), sequence) << "r2's own update waited for its move";
  }
  EXPECT_LT(builds, 20) << "a robot that sends a map for every build never ends its move";
  const std::uint64_t stop = version + 20;
  while (builder.deferred() && version < stop) {
    last = builder.build(registry, ++version);
    ASSERT_TRUE(last);
  }
  EXPECT_FALSE(builder.deferred());
  EXPECT_EQ(sequence_of(*last, "r2"), sequence);
  const auto expected_again = GlobalMapBuilder(config).build(registry, 99);
  ASSERT_TRUE(expected_again);
  EXPECT_TRUE(last->data == expected_again->data) << "after the second move, the map differs from a fresh build";
}

TEST(ExportGlobal, WritesTheLastGlobalMapAndWhichRobotContributedEachVoxel) {
  const auto world = test::load_data_map("geb079.bt");
  const Eigen::Matrix4d T2 = mapmerge::paper_transform(-4, 7, 0.3, -3, 2, 155);
  const std::vector<test::RobotMap> robots{test::cut_robot_map(*world, "r1", box(-8, 12), Eigen::Matrix4d::Identity()),
                                           test::cut_robot_map(*world, "r2", box(4, 24), T2)};
  ServerConfig config;
  config.store.state_dir = test::temp_dir("export_unit");
  Registry registry;
  registry.claim_reference("r1");
  {
    Store store(config.store);
    for (const auto& r : robots) {
      MapSample m;
      m.robot_id = m.topic_robot = r.id;
      m.session_id = "s1";
      m.sequence = 1;
      m.encoding = "octomap-bt";
      m.data = encode_map(*r.tree, Encoding::kOctomapBt);
      store.save_map(m);
      registry.put_map(record_of(r, 1));
    }
    registry.put_edge(Edge{"r1", "r2", T2.inverse(), 0.02});
    const auto g = GlobalMapBuilder(config).build(registry, 5);
    ASSERT_TRUE(g);
    store.save_global(*g, pose_outputs(registry));
  }
  const std::string prefix = config.store.state_dir + "/global";
  const ExportedGlobal e = export_global(config, prefix);
  EXPECT_EQ(e.version, 5u);
  EXPECT_EQ(e.robots, 2u);
  const auto map = read_octree_file(prefix + ".bt");
  const Provenance p = read_provenance(prefix + ".prov");
  ASSERT_EQ(p.robots.size(), 2u);
  EXPECT_EQ(p.robots[0].name, "r1");
  EXPECT_EQ(p.robots[1].name, "r2");
  EXPECT_TRUE(p.robots[1].T_global_robot.isApprox(T2.inverse(), 1e-6));  // the published pose
  EXPECT_DOUBLE_EQ(p.resolution, map->getResolution());
  std::size_t by[2] = {0, 0};
  for (const auto& [key, owner] : p.owner) {
    ASSERT_LT(owner.robot, 2u);
    ++by[owner.robot];
    const octomap::OcTreeNode* n = map->search(key);
    ASSERT_NE(n, nullptr);  // provenance lies on the exported map's grid
  }
  EXPECT_GT(by[0], 10000u);
  EXPECT_GT(by[1], 10000u);
  // A store without a global map is an error, not an empty export.
  ServerConfig empty;
  empty.store.state_dir = test::temp_dir("export_empty");
  EXPECT_THROW(export_global(empty, empty.store.state_dir + "/global"), StoreError);
}

TEST(ServerExitCodes, UsageAndStoreErrorsAreDistinct) {
  const std::string dir = test::temp_dir("exit_codes");
  const auto run = [&](const std::vector<std::string>& args) {
    test::ServerProcess p(args, dir + "/server.log");
    return p.wait(std::chrono::seconds(30));
  };
  EXPECT_EQ(run({"--domain", "300"}), 2);
  std::ofstream(dir + "/bad.yaml") << "merge: {threads: 0}\n";
  EXPECT_EQ(run({"--config", dir + "/bad.yaml"}), 2);
  EXPECT_EQ(run({"--state-dir", "/proc/mapmerge-cannot-exist", "--domain", "101"}), 3);
}

}  // namespace
}  // namespace mapmerge::server
