# Run-time defaults of a MAPMERGE_SANITIZE build (see README, "Sanitizers and fuzzing").
#
# ASan: new_delete_type_mismatch is off because Fast DDS 2.9.1 (Debian 12) deletes its
#   StatisticsWriterImpl through the RTPSWriter/RTPSReader base with the base's size
#   (~RTPSWriter, ~RTPSReader in libfastrtps.so.2.9): every DDS program aborts on it at the first
#   endpoint deleted. ASan's suppressions file cannot scope this check to a library, so it is off
#   for the whole sanitized build; all other ASan checks stay on.
# LSan: tests/sanitizers/lsan.supp (third-party leaks only, each with its reason).
# UBSan: every finding is already fatal (-fno-sanitize-recover=undefined); print the stack.
set(MAPMERGE_ASAN_OPTIONS "new_delete_type_mismatch=0:check_initialization_order=1:detect_leaks=1")
set(MAPMERGE_LSAN_OPTIONS "suppressions=${PROJECT_SOURCE_DIR}/tests/sanitizers/lsan.supp:print_suppressions=0")
set(MAPMERGE_UBSAN_OPTIONS "print_stacktrace=1")
# For tests that build or run programs outside this build (ctest ENVIRONMENT).
set(MAPMERGE_SANITIZER_ENV "ASAN_OPTIONS=${MAPMERGE_ASAN_OPTIONS}" "LSAN_OPTIONS=${MAPMERGE_LSAN_OPTIONS}"
    "UBSAN_OPTIONS=${MAPMERGE_UBSAN_OPTIONS}")

# Appends the executables defined in `dir` and below to the list `out`.
function(_mapmerge_executables dir out)
  get_property(targets DIRECTORY ${dir} PROPERTY BUILDSYSTEM_TARGETS)
  get_property(subdirs DIRECTORY ${dir} PROPERTY SUBDIRECTORIES)
  set(found ${${out}})
  foreach(t IN LISTS targets)
    get_target_property(type ${t} TYPE)
    if(type STREQUAL "EXECUTABLE")
      list(APPEND found ${t})
    endif()
  endforeach()
  foreach(d IN LISTS subdirs)
    _mapmerge_executables(${d} found)
  endforeach()
  set(${out} ${found} PARENT_SCOPE)
endfunction()

# Links the defaults into every executable of the project; call once, after all subdirectories.
function(mapmerge_sanitizer_defaults)
  configure_file(${PROJECT_SOURCE_DIR}/tests/sanitizers/defaults.cpp.in
                 ${PROJECT_BINARY_DIR}/sanitizer_defaults.cpp @ONLY)
  add_library(mapmerge_sanitizer_defaults OBJECT ${PROJECT_BINARY_DIR}/sanitizer_defaults.cpp)
  set(executables "")
  _mapmerge_executables(${PROJECT_SOURCE_DIR} executables)
  foreach(t IN LISTS executables)
    target_link_libraries(${t} PRIVATE mapmerge_sanitizer_defaults)
  endforeach()
endfunction()
