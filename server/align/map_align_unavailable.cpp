// alignMaps() in a build without Open3D (cmake -DSTEREOMAP_ALIGN=OFF: the Docker images,
// whose size Open3D's runtime would triple): every call says so.
#include "server/align/map_align.hpp"

namespace stereomap::align {

common::Result<Alignment> alignMaps(const fusion::OccupancyMap&, const fusion::OccupancyMap&,
                                    const AlignOptions&) {
  return common::makeError(common::ErrorCode::kUnavailable,
                           "this build has no map alignment (built without Open3D: "
                           "STEREOMAP_ALIGN=OFF, as the Docker images are); run stereomap-store "
                           "align from a full build");
}

}  // namespace stereomap::align
