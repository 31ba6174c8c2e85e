#include "common/url.hpp"

#include <gtest/gtest.h>

namespace stereomap::common {
namespace {

TEST(Url, QueryParametersAreDecodedAndMatchedWhole) {
  EXPECT_EQ(queryParameter("/ws?a=1&token=x%2By", "token"), "x+y");
  EXPECT_EQ(queryParameter("/ws?xtoken=1", "token"), std::nullopt);
  EXPECT_EQ(queryParameter("/ws?token=%zz", "token"), std::nullopt);
  EXPECT_EQ(percentDecoded("%00"), std::nullopt);
}

TEST(Url, AHeaderListHoldsAnItemOnlyWhole) {
  EXPECT_TRUE(listsToken("foxglove.websocket.v1", "foxglove.websocket.v1"));
  EXPECT_TRUE(listsToken("foxglove.sdk.v1, foxglove.websocket.v1", "foxglove.websocket.v1"));
  EXPECT_TRUE(listsToken(" a ,\tfoxglove.sdk.v1\t", "foxglove.sdk.v1"));
  EXPECT_FALSE(listsToken("foxglove.websocket.v10", "foxglove.websocket.v1"));
  EXPECT_FALSE(listsToken("xfoxglove.websocket.v1", "foxglove.websocket.v1"));
  EXPECT_FALSE(listsToken("Foxglove.websocket.v1", "foxglove.websocket.v1"));
  EXPECT_FALSE(listsToken("", "foxglove.websocket.v1"));
  EXPECT_FALSE(listsToken(",,", "foxglove.websocket.v1"));
}

}  // namespace
}  // namespace stereomap::common
