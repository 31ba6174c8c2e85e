#include "proto/qos.hpp"

namespace stereomap::proto {

namespace {
dds_qos_t* reliable(int depth) {
  dds_qos_t* qos = dds_create_qos();
  dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_SECS(2));
  dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, depth);
  return qos;
}
}  // namespace

dds_qos_t* sessionEventQos() {
  dds_qos_t* qos = reliable(4);
  dds_qset_durability(qos, DDS_DURABILITY_TRANSIENT_LOCAL);
  return qos;
}

dds_qos_t* poseQos() {
  dds_qos_t* qos = reliable(kPoseHistory);
  dds_qset_durability(qos, DDS_DURABILITY_TRANSIENT_LOCAL);
  return qos;
}

dds_qos_t* poseReaderQos() {
  dds_qos_t* qos = poseQos();
  dds_qset_history(qos, DDS_HISTORY_KEEP_ALL, 0);
  return qos;
}

dds_qos_t* cloudQos() {
  dds_qos_t* qos = reliable(kCloudHistory);
  dds_qset_durability(qos, DDS_DURABILITY_TRANSIENT_LOCAL);
  return qos;
}

dds_qos_t* cloudReaderQos() {
  dds_qos_t* qos = cloudQos();
  dds_qset_history(qos, DDS_HISTORY_KEEP_ALL, 0);
  return qos;
}

}  // namespace stereomap::proto
