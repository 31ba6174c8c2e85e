#include "server/core/metrics.hpp"

#include <gtest/gtest.h>

namespace stereomap::core {
namespace {

TEST(Metrics, RendersFamiliesWithTheirHelpTypeAndSeries) {
  Metrics metrics;
  metrics.describe("frames_total", "counter", "Frames taken");
  metrics.add("frames_total", {{"session", "a"}});
  metrics.add("frames_total", {{"session", "a"}}, 2);
  metrics.set("backlog", {}, 7);
  metrics.set("backlog", {}, 3);  // a gauge is replaced, not added to
  EXPECT_EQ(metrics.get("frames_total", {{"session", "a"}}), 3.0);
  EXPECT_EQ(metrics.get("frames_total", {{"session", "b"}}), 0.0);
  EXPECT_EQ(metrics.get("unknown", {}), 0.0);
  EXPECT_EQ(metrics.render(),
            "backlog 3\n"
            "# HELP frames_total Frames taken\n"
            "# TYPE frames_total counter\n"
            "frames_total{session=\"a\"} 3\n");
}

// Byte counts and totals are exact, not rounded to six digits.
TEST(Metrics, RendersLargeCountsExactly) {
  Metrics metrics;
  metrics.set("bytes", {}, 38123520);
  metrics.set("seconds", {}, 0.1 + 0.2);
  EXPECT_EQ(metrics.render(), "bytes 38123520\nseconds 0.3\n");
}

// Label values come from outside (session and vehicle ids, rejection details): a quote, a
// backslash or a line break must not end the value or the line.
TEST(Metrics, EscapesLabelValuesAsTheExpositionFormatSays) {
  Metrics metrics;
  metrics.add("x", {{"id", "a\"b\\c\nd"}, {"k", "v"}});
  EXPECT_EQ(metrics.render(), "x{id=\"a\\\"b\\\\c\\nd\",k=\"v\"} 1\n");
}

TEST(Metrics, RemovesEverySeriesOfOneLabelValueAndNoOther) {
  Metrics metrics;
  metrics.add("a_total", {{"session", "s"}, {"vehicle", "v"}});
  metrics.add("a_total", {{"vehicle", "v"}, {"session", "s"}});
  metrics.add("a_total", {{"session", "s2"}});
  metrics.set("b", {{"session", "s"}}, 1);
  metrics.set("b", {{"vehicle", "s"}}, 1);                // the value under another label
  metrics.set("b", {{"session", "x,session=\"s\""}}, 1);  // the pair inside a value
  metrics.removeSeries("session", "s");
  EXPECT_EQ(metrics.render(),
            "a_total{session=\"s2\"} 1\n"
            "b{session=\"x,session=\\\"s\\\"\"} 1\n"
            "b{vehicle=\"s\"} 1\n");
}

}  // namespace
}  // namespace stereomap::core
