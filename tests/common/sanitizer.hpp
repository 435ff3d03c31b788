#pragma once
/// How much longer a test waits for work our code does, when that code runs under AddressSanitizer
/// (build-asan/: -O1 and instrumented, 2-3 times slower; e.g. `mapmerge scenario` on fr_079).

namespace mapmerge::test {

#ifdef MAPMERGE_SANITIZE_BUILD  // set by CMake with MAPMERGE_SANITIZE=ON
inline constexpr int kSanitizerSlowdown = 3;  ///< factor on waits for our own computation [-]
#else
inline constexpr int kSanitizerSlowdown = 1;  ///< factor on waits for our own computation [-]
#endif

}  // namespace mapmerge::test
