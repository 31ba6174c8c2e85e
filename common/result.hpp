// Result<T>: a value or an Error with a category and a message naming what was wrong.
// Used for every fallible operation on input from outside (files, flags, network, DDS
// samples); exceptions are only thrown at start-up boundaries (apps).
#pragma once

#include <string>
#include <utility>
#include <variant>

namespace stereomap::common {

// kConflict: the request clashes with the current state (already loaded, live, exists).
enum class ErrorCode {
  kInvalidArgument,
  kNotFound,
  kIo,
  kCorrupt,
  kTooLarge,
  kUnavailable,
  kConflict
};

struct Error {
  ErrorCode code = ErrorCode::kInvalidArgument;
  std::string message;
};

template <typename T>
class [[nodiscard]] Result {
 public:
  Result(T value) : state_(std::move(value)) {}      // NOLINT: implicit by design
  Result(Error error) : state_(std::move(error)) {}  // NOLINT

  bool ok() const { return std::holds_alternative<T>(state_); }
  explicit operator bool() const { return ok(); }
  T& value() & { return std::get<T>(state_); }
  const T& value() const& { return std::get<T>(state_); }
  T&& value() && { return std::get<T>(std::move(state_)); }
  T* operator->() { return &value(); }
  const T* operator->() const { return &value(); }
  T& operator*() & { return value(); }
  const T& operator*() const& { return value(); }
  const Error& error() const { return std::get<Error>(state_); }

 private:
  std::variant<T, Error> state_;
};

// Result for operations with no value.
struct Ok {};
using Status = Result<Ok>;

inline Error makeError(ErrorCode code, std::string message) { return {code, std::move(message)}; }

}  // namespace stereomap::common
