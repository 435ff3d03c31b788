# Installs the client component of a build tree into a fresh prefix, then configures, builds
# and runs a tiny consumer project against it (find_package(mapmerge), mapmerge::client).
#   cmake -DBUILD_DIR=... -DCONSUMER_DIR=... -DWORK_DIR=... -DGENERATOR=... -DCONSUMER_CXX=...
#         [-DCONSUMER_FLAGS=...] -P install_consumer_test.cmake
# (CONSUMER_CXX/FLAGS: the build's compiler and sanitizer flags, which the consumer must share.)
function(run)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
  if(NOT rc EQUAL 0)
    message(FATAL_ERROR "failed (${rc}): ${ARGN}\n${out}\n${err}")
  endif()
endfunction()

set(domain 0)
if(DEFINED ENV{CTEST_RESOURCE_GROUP_0_DOMAINS})
  string(REGEX MATCH "id:([0-9]+)" _ "$ENV{CTEST_RESOURCE_GROUP_0_DOMAINS}")
  set(domain ${CMAKE_MATCH_1})
endif()

file(REMOVE_RECURSE ${WORK_DIR})
set(prefix ${WORK_DIR}/prefix)
run(${CMAKE_COMMAND} --install ${BUILD_DIR} --component mapmerge_client --prefix ${prefix})
# The installed headers must be the client's own, usable without the source tree.
file(GLOB_RECURSE headers RELATIVE ${prefix}/include ${prefix}/include/*)
if(NOT headers STREQUAL "mapmerge/client/client.hpp")
  message(FATAL_ERROR "unexpected installed headers: ${headers}")
endif()
run(${CMAKE_COMMAND} -S ${CONSUMER_DIR} -B ${WORK_DIR}/build -G ${GENERATOR} -DCMAKE_PREFIX_PATH=${prefix}
    -DCMAKE_CXX_COMPILER=${CONSUMER_CXX} "-DCMAKE_CXX_FLAGS=${CONSUMER_FLAGS}")
run(${CMAKE_COMMAND} --build ${WORK_DIR}/build)
run(${WORK_DIR}/build/consumer ${domain})
file(REMOVE_RECURSE ${WORK_DIR})
message(STATUS "installed mapmerge::client consumed from ${prefix}")
