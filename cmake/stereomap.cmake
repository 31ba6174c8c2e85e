# Shared settings for every stereomap target (not applied to generated IDL code).

function(stereomap_target_defaults target)
  # Designated initializers leave members at their defaults on purpose.
  target_compile_options(${target} PRIVATE -Wall -Wextra -Werror -Wno-missing-field-initializers)
endfunction()

# Every binary (test, app, bench): under ThreadSanitizer, OpenCV runs serially
# (common/tsan_serial_opencv.cpp says why).
function(stereomap_binary_defaults target)
  stereomap_target_defaults(${target})
  if(STEREOMAP_SANITIZE MATCHES "thread")
    target_sources(${target} PRIVATE ${PROJECT_SOURCE_DIR}/common/tsan_serial_opencv.cpp)
    target_link_libraries(${target} PRIVATE opencv_core)
  endif()
endfunction()

# stereomap_library(NAME SOURCES ... DEPS ...): one library per concern, explicit sources.
function(stereomap_library name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS;PRIVATE_DEPS" ${ARGN})
  add_library(${name} STATIC ${ARG_SOURCES})
  target_include_directories(${name} PUBLIC ${PROJECT_SOURCE_DIR})
  target_link_libraries(${name} PUBLIC ${ARG_DEPS} PRIVATE ${ARG_PRIVATE_DEPS})
  stereomap_target_defaults(${name})
endfunction()

# stereomap_test(NAME [SERIAL] SOURCES ... DEPS ...): a GoogleTest binary registered with
# CTest, its test cases labelled NAME. SERIAL: its tests run alone (they measure time, which a test beside them on the
# machine's two cores would spoil).
# A test case's time limit (s): sanitised builds run several times slower (CMakePresets.json).
set(STEREOMAP_TEST_TIMEOUT 300 CACHE STRING "Seconds before CTest stops a test case")
function(stereomap_test name)
  cmake_parse_arguments(ARG "SERIAL" "" "SOURCES;DEPS" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS} GTest::gtest_main GTest::gmock)
  target_compile_definitions(${name} PRIVATE
    STEREOMAP_DATA_DIR="${STEREOMAP_DATA_DIR}"
    STEREOMAP_DDS_CONFIG="${STEREOMAP_DDS_CONFIG}"
    STEREOMAP_BIN_DIR="${CMAKE_RUNTIME_OUTPUT_DIRECTORY}")
  set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${CMAKE_BINARY_DIR}/tests)
  stereomap_binary_defaults(${name})
  set(serial FALSE)
  if(ARG_SERIAL)
    set(serial TRUE)
  endif()
  # Each test case is labelled with its binary, so that a run can pick binaries (ctest -L).
  gtest_discover_tests(${name} DISCOVERY_TIMEOUT 60
    PROPERTIES TIMEOUT ${STEREOMAP_TEST_TIMEOUT} RUN_SERIAL ${serial} LABELS ${name})
endfunction()

# stereomap_app(NAME SOURCES ... DEPS ...): a stereomap-<verb> binary in build/bin.
function(stereomap_app name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPS" ${ARGN})
  add_executable(${name} ${ARG_SOURCES})
  target_link_libraries(${name} PRIVATE ${ARG_DEPS} CLI11::CLI11)
  stereomap_binary_defaults(${name})
endfunction()

# stereomap_bench(NAME SOURCES ... DEPS ... [DATA] [JEMALLOC]): the benchmark binary
# stereomap-bench-NAME in build/bin (figures for docs/BENCHMARKS.md). DATA: it reads the shared
# data sets (STEREOMAP_DATA_DIR); JEMALLOC: it allocates as the server does.
function(stereomap_bench name)
  cmake_parse_arguments(ARG "DATA;JEMALLOC" "" "SOURCES;DEPS" ${ARGN})
  set(target stereomap-bench-${name})
  add_executable(${target} ${ARG_SOURCES})
  target_link_libraries(${target} PRIVATE ${ARG_DEPS})
  if(ARG_DATA)
    target_compile_definitions(${target} PRIVATE STEREOMAP_DATA_DIR="${STEREOMAP_DATA_DIR}")
  endif()
  if(ARG_JEMALLOC)
    stereomap_use_jemalloc(${target})
  endif()
  stereomap_binary_defaults(${target})
endfunction()
