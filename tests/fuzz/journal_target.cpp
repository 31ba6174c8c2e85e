// Fuzz target: a session journal as the server reads it after a crash or a disk fault
// (server/store/journal). The input is the whole file. Reading must keep whatever is whole
// and report the rest; opening it for appending must cut or set aside what is not whole, so
// that a record appended next is read back as the file's last, numbered above every other.
#include <variant>

#include "proto/journal/journal.hpp"
#include "tests/fuzz/fuzz_input.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace stereomap;
  const auto path =
      fuzz::scratch().write("journal.smj", {reinterpret_cast<const char*>(data), size});
  auto replay = proto::journal::readJournal(path);
  if (!replay) __builtin_trap();  // the file exists: damage is reported, not an error
  if (replay->records.size() != replay->numbers.size() || replay->good_bytes > size ||
      replay->file_bytes != size) {
    __builtin_trap();
  }

  auto journal = proto::journal::Journal::open(path);
  if (!journal) return 0;  // refused (a format 1 file, or a tail it could not set aside)
  proto::PoseMsg pose;
  pose.vehicle_id.assign(1, 'v');  // (gcc 12 warns falsely on = "v": -Wrestrict)
  pose.session_id.assign(1, 's');
  auto number = (*journal)->append(pose);
  if (!number || *number <= replay->last_number) __builtin_trap();
  journal->reset();
  auto again = proto::journal::readJournal(path);
  if (!again || again->numbers.empty() || again->numbers.back() != *number ||
      !std::holds_alternative<proto::PoseMsg>(again->records.back())) {
    __builtin_trap();
  }
  for (const auto& entry : std::filesystem::directory_iterator(fuzz::scratch().path())) {
    std::filesystem::remove(entry.path());  // set-aside tails
  }
  return 0;
}
