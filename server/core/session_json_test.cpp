#include "server/core/session_json.hpp"

#include <gtest/gtest.h>

namespace stereomap::core {
namespace {

using nlohmann::json;

SessionStatus sample() {
  SessionStatus s;
  s.id = "flight-1";
  s.vehicles = {"v1", "v2"};
  s.resolution = 0.05;
  s.frames_received = 12;
  s.frames_fused = 10;
  s.frames_dropped = 2;
  s.occupied_voxels = 345;
  s.bounds.extend({-1, -2, -3});
  s.bounds.extend({4, 5, 6});
  s.poses = 99;
  s.bytes_received = 5'000'000'000;  // past 32 bits
  s.ended = true;
  s.ended_by = "silence";
  s.samples_refused = 3;
  s.corrections = 4;
  s.refusions = 5;
  return s;
}

TEST(SessionJson, WhatIsWrittenReadsBack) {
  const SessionStatus written = sample();
  const json object = json::parse(sessionJson(written));
  EXPECT_EQ(object["state"], "ended");
  EXPECT_EQ(object["vehicle"], "v1");
  EXPECT_EQ(object["store_error"], nullptr);
  // The cumulative counts a viewer derives clouds/s, poses/s and the link's kB/s from.
  EXPECT_EQ(object["frames_received"], 12u);
  EXPECT_EQ(object["poses"], 99u);
  EXPECT_EQ(object["bytes_received"], 5'000'000'000u);
  const SessionStatus read = sessionFromJson("flight-1", object);
  EXPECT_EQ(read.vehicles, written.vehicles);
  EXPECT_EQ(read.resolution, written.resolution);
  EXPECT_EQ(read.frames_received, written.frames_received);
  EXPECT_EQ(read.frames_fused, written.frames_fused);
  EXPECT_EQ(read.frames_dropped, written.frames_dropped);
  EXPECT_EQ(read.occupied_voxels, written.occupied_voxels);
  EXPECT_EQ(read.poses, written.poses);
  EXPECT_EQ(read.bytes_received, written.bytes_received);
  EXPECT_EQ(read.ended_by, written.ended_by);
  EXPECT_EQ(read.samples_refused, written.samples_refused);
  EXPECT_EQ(read.corrections, written.corrections);
  EXPECT_EQ(read.refusions, written.refusions);
  EXPECT_EQ(read.bounds.min, written.bounds.min);
  EXPECT_EQ(read.bounds.max, written.bounds.max);
  EXPECT_EQ(std::string(stateName(read)), "ended");
  // Every state reads back as itself.
  for (const char* state : {"live", "ended", "opened", "closed"}) {
    EXPECT_EQ(std::string(stateName(sessionFromJson("x", json{{"state", state}}))), state);
  }
}

TEST(SessionJson, AViewerMessageSaysItsType) {
  EXPECT_EQ(json::parse(sessionJson(sample(), "session"))["type"], "session");
  EXPECT_FALSE(json::parse(sessionJson(sample())).contains("type"));
}

TEST(SessionJson, TheCatalogsFieldsAreTheSameKeysWithTheSameValues) {
  const json all = sessionObject(sample());
  const json kept = sessionObject(sample(), SessionFields::kCatalog);
  EXPECT_EQ(kept.size(), 8u);
  for (const auto& [key, value] : kept.items()) EXPECT_EQ(all.at(key), value) << key;
}

// session.json is a file on disk: damaged or foreign content gives defaults, never a throw,
// and the id is the caller's (the directory's), never the file's.
TEST(SessionJson, ADamagedDocumentGivesDefaults) {
  const json damaged = {{"id", "../etc"},       {"vehicles", {1, "v1", nullptr}},
                        {"resolution", "fine"}, {"frames", -4},
                        {"poses", 1.5},         {"bounds", {{"min", {1, 2}}, {"max", "x"}}},
                        {"ended_by", 7}};
  const SessionStatus read = sessionFromJson("s1", damaged);
  EXPECT_EQ(read.id, "s1");
  EXPECT_EQ(read.vehicles, std::vector<std::string>{"v1"});
  EXPECT_EQ(read.resolution, 0);
  EXPECT_EQ(read.frames_fused, 0u);
  EXPECT_EQ(read.poses, 0u);
  EXPECT_TRUE(read.bounds.empty());
  EXPECT_EQ(read.ended_by, "");
  EXPECT_TRUE(read.ended);  // no state: it stopped unsaved
  for (const json& not_an_object : {json(nullptr), json::array(), json("text"), json(3)}) {
    const SessionStatus s = sessionFromJson("s2", not_an_object);
    EXPECT_EQ(s.id, "s2");
    EXPECT_TRUE(s.ended);
  }
}

}  // namespace
}  // namespace stereomap::core
