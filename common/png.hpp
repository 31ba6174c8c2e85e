// A greyscale PNG writer (8 bits per pixel, zlib from the system): enough for the server's
// top-view exports without linking an imaging library into the server and its image.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace stereomap::common {

// `pixels` holds `height` rows of `width` bytes, top row first. Returns the PNG file's bytes;
// empty when the size is zero or the pixel count does not match.
std::string encodeGreyPng(const std::vector<uint8_t>& pixels, uint32_t width, uint32_t height);

}  // namespace stereomap::common
