#include "proto/detail/qos.hpp"

namespace stereomap::proto {

namespace {

// Reliable and transient-local: a writer keeps its last `depth` samples for readers that
// join late (a restarted server).
dds_qos_t* reliableWithHistory(int depth) {
  dds_qos_t* qos = dds_create_qos();
  dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_SECS(2));
  dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, depth);
  dds_qset_durability(qos, DDS_DURABILITY_TRANSIENT_LOCAL);
  return qos;
}

// The reader's side of it: keep-all, so a backlog of history is never overwritten unread.
dds_qos_t* keepingAll(dds_qos_t* qos) {
  dds_qset_history(qos, DDS_HISTORY_KEEP_ALL, 0);
  return qos;
}

// Reliable, volatile, keep-last 1 per instance: only the newest sample matters.
dds_qos_t* newestOnly() {
  dds_qos_t* qos = dds_create_qos();
  dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
  dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, 1);
  dds_qset_durability(qos, DDS_DURABILITY_VOLATILE);
  return qos;
}

}  // namespace

dds_qos_t* sessionEventQos() { return reliableWithHistory(4); }
dds_qos_t* poseCorrectionQos() { return reliableWithHistory(1); }
dds_qos_t* landingTargetQos() { return newestOnly(); }
dds_qos_t* ackQos() { return newestOnly(); }
dds_qos_t* vehicleStatusQos() { return newestOnly(); }
dds_qos_t* poseQos() { return reliableWithHistory(kPoseHistory); }
dds_qos_t* poseReaderQos() { return keepingAll(poseQos()); }
dds_qos_t* cloudQos() { return reliableWithHistory(kCloudHistory); }
dds_qos_t* cloudReaderQos() { return keepingAll(cloudQos()); }

}  // namespace stereomap::proto
