#pragma once
/// How much longer a test waits for work our code does, when that code runs under AddressSanitizer
/// (build-asan/: -O1 and instrumented, 2-3 times slower; e.g. `mapmerge scenario` on fr_079).

#if defined(__SANITIZE_ADDRESS__)
#define MAPMERGE_TEST_ASAN 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define MAPMERGE_TEST_ASAN 1
#endif
#endif

namespace mapmerge::test {

#ifdef MAPMERGE_TEST_ASAN
inline constexpr int kSanitizerSlowdown = 3;  ///< factor on waits for our own computation [-]
#else
inline constexpr int kSanitizerSlowdown = 1;  ///< factor on waits for our own computation [-]
#endif

}  // namespace mapmerge::test
