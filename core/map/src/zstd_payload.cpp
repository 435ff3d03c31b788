#include <algorithm>
#include <memory>

#include <zstd.h>

#include "codec_detail.hpp"
#include "mapmerge/map/map_io.hpp"

namespace mapmerge::detail {

std::optional<DecodeResult> inflate(const std::uint8_t* data, std::size_t size,
                                    const DecodeLimits& limits, std::vector<std::uint8_t>& out) {
  if (!is_zstd(data, size)) {
    if (starts_with(data, size, "# Octomap")) {
      return rejected(DecodeError::kEncodingMismatch,
                      "payload is an uncompressed OctoMap but the encoding is octomap-bt+zstd");
    }
    return rejected(DecodeError::kDecompressionFailed, "payload is not a zstd frame");
  }
  const unsigned long long declared = ZSTD_getFrameContentSize(data, size);
  if (declared == ZSTD_CONTENTSIZE_ERROR) {
    return rejected(DecodeError::kDecompressionFailed, "corrupt zstd frame header");
  }
  if (declared != ZSTD_CONTENTSIZE_UNKNOWN && declared >= limits.max_bytes) {
    return rejected(DecodeError::kTooLarge, "zstd frame declares " + std::to_string(declared) +
                                                " bytes, limit " +
                                                std::to_string(limits.max_bytes));
  }
  std::unique_ptr<ZSTD_DCtx, decltype(&ZSTD_freeDCtx)> ctx(ZSTD_createDCtx(), &ZSTD_freeDCtx);
  if (!ctx) return rejected(DecodeError::kDecompressionFailed, "cannot create zstd context");
  out.clear();
  out.resize(declared != ZSTD_CONTENTSIZE_UNKNOWN ? static_cast<std::size_t>(declared) + 1
                                                  : std::min<std::size_t>(4 * size, limits.max_bytes));
  ZSTD_inBuffer in{data, size, 0};
  std::size_t produced = 0;
  std::size_t last = 1;
  while (in.pos < in.size || last != 0) {
    if (produced == out.size()) {
      if (out.size() >= limits.max_bytes) {
        return rejected(DecodeError::kTooLarge, "decompresses to " + std::to_string(limits.max_bytes) +
                                                    " bytes or more (the limit)");
      }
      out.resize(std::min(limits.max_bytes, 2 * out.size() + 4096));
    }
    ZSTD_outBuffer ob{out.data(), out.size(), produced};
    const std::size_t before_in = in.pos;
    last = ZSTD_decompressStream(ctx.get(), &ob, &in);
    if (ZSTD_isError(last)) {
      return rejected(DecodeError::kDecompressionFailed, ZSTD_getErrorName(last));
    }
    const bool progress = ob.pos != produced || in.pos != before_in;
    produced = ob.pos;
    if (!progress && produced < out.size()) {
      return rejected(DecodeError::kDecompressionFailed, "zstd frame is incomplete");
    }
  }
  if (produced >= limits.max_bytes) {
    return rejected(DecodeError::kTooLarge, "decompresses to " + std::to_string(produced) +
                                                " bytes or more, limit " +
                                                std::to_string(limits.max_bytes));
  }
  out.resize(produced);
  return std::nullopt;
}

std::vector<std::uint8_t> deflate(const std::vector<std::uint8_t>& raw, int level) {
  // The frame carries its content size (lets the receiver reject oversize before inflating)
  // and a checksum (a corrupted payload fails to decompress instead of yielding other bytes).
  std::unique_ptr<ZSTD_CCtx, decltype(&ZSTD_freeCCtx)> ctx(ZSTD_createCCtx(), &ZSTD_freeCCtx);
  if (!ctx) throw MapError("cannot create a zstd context");
  ZSTD_CCtx_setParameter(ctx.get(), ZSTD_c_compressionLevel, level);
  ZSTD_CCtx_setParameter(ctx.get(), ZSTD_c_checksumFlag, 1);
  std::vector<std::uint8_t> packed(ZSTD_compressBound(raw.size()));
  const std::size_t n = ZSTD_compress2(ctx.get(), packed.data(), packed.size(), raw.data(), raw.size());
  if (ZSTD_isError(n)) throw MapError(std::string("zstd compression failed: ") + ZSTD_getErrorName(n));
  packed.resize(n);
  return packed;
}

}  // namespace mapmerge::detail
