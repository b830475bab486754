// CPU inference kernels for bench/nn (plain C ABI, called through ctypes by bench/nn/native.py; no
// torch headers, so it compiles in a few seconds). Tensors come as base pointers plus element strides,
// float32 or bfloat16 (dtype codes below); sums are float32. Each kernel replaces eager PyTorch ops
// that are memory-bound at 1080p: it keeps per-pixel intermediates in registers instead of writing
// them to memory and reading them back.
//
// deform_columns: bilinear sampling of the deformable conv's inference sampler (bench/nn/deform.py):
// the im2col columns of a strip of output pixels, col[p][k*C + ch] = mask_k(p) * x[ch] sampled
// bilinearly at tap k's position of pixel p, which one 1x1 conv (oneDNN, the 3x3 conv's MACs) then
// turns into the output. Eager PyTorch needs index and weight tensors for every corner (36 per pixel,
// written and read back); here positions, weights and the 4-corner sums stay in registers, and the
// strip's columns stay in cache for the conv that follows. Semantics of the eager sampler: every
// bilinear corner outside the image reads zero, positions are clamped to [-1, H] x [-1, W] first (so
// huge or infinite offsets read zeros), and a NaN position gives NaN columns (so a NaN pixel).
//
// deform_columns_backward: the gradient of deform_columns (training, float32): from the gradient of
// the columns, the input's (scattered to the 4 corners of every sample), the offsets' (the derivative
// of the bilinear sample along y and x, summed over channels) and the mask's. Same semantics: a
// position clamped to the border has zero offset gradient (as torch.clamp's), corners outside the
// image get nothing, a NaN position gives NaN offset and mask gradients.
//
// cfm_affine: conditioned feature modulation (bench/nn/cfm.py), x * (1 + gamma) + beta with gamma and
// beta 1x1 convs of the conditioning features, optionally followed by ReLU, in one pass per pixel:
// eager PyTorch writes the 2C-channel gamma/beta map and two intermediates at full resolution.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>

#if defined(__AVX512BF16__)
#include <immintrin.h>
#endif

namespace {

enum Dtype : int32_t { kFloat32 = 0, kBFloat16 = 1 };

inline float to_float(float v) { return v; }
inline float to_float(uint16_t bits) {  // bfloat16
    uint32_t u = static_cast<uint32_t>(bits) << 16;
    float f;
    std::memcpy(&f, &u, sizeof f);
    return f;
}

inline void store(float* dst, float v) { *dst = v; }
inline void store(uint16_t* dst, float v) {  // to bfloat16, round to nearest even as torch does
    uint32_t u;
    std::memcpy(&u, &v, sizeof u);
    *dst = (u & 0x7fffffffu) > 0x7f800000u ? uint16_t{0x7fc0}
                                           : static_cast<uint16_t>((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

// A 4-D tensor (b, channel, row, col) given by its base pointer, dtype and element strides.
struct View {
    const void* data;
    int32_t dtype;
    int64_t s0, s1, s2, s3;
    // n values along the last axis from (b, ch, r, c), as float32
    void run(int64_t b, int64_t ch, int64_t r, int64_t c, int64_t n, float* dst) const {
        const int64_t i = b * s0 + ch * s1 + r * s2 + c * s3;
        if (dtype == kBFloat16) {
            const uint16_t* src = static_cast<const uint16_t*>(data) + i;
            for (int64_t j = 0; j < n; ++j) dst[j] = to_float(src[j * s3]);
        } else {
            const float* src = static_cast<const float*>(data) + i;
            for (int64_t j = 0; j < n; ++j) dst[j] = src[j * s3];
        }
    }
};

struct Geometry {
    int64_t in_h, in_w, out_w, taps;
    const int64_t* tap_y;  // per tap k = i*kw + j: i*dilation - padding
    const int64_t* tap_x;  // j*dilation - padding
};

// Runs fn(begin, end) over [0, count) split among `threads` OpenMP threads. bench/nn/native.py links
// this file against the libgomp torch already loaded, so these are torch's own pool threads: a second
// pool would fight torch's spinning workers for the cores after every torch op.
template <typename Fn>
void parallel_for(int64_t count, int32_t threads, const Fn& fn) {
    threads = static_cast<int32_t>(std::max<int64_t>(1, std::min<int64_t>(threads, count)));
#pragma omp parallel for num_threads(threads) schedule(static, 1)
    for (int32_t t = 0; t < threads; ++t) fn(count * t / threads, count * (t + 1) / threads);
}

// kWidth floats per vector: one register of this CPU's widest float unit, 16 with AVX-512 and 8 without.
// GCC's generic vector types must not be wider than the hardware's: a 64-byte vector on an AVX2 CPU
// is split through the stack, and every scalar broadcast becomes a store and a reload (measured: the
// sampling ran 4x slower than with 32-byte vectors).
#if defined(__AVX512F__)
constexpr int kWidth = 16;
#else
constexpr int kWidth = 8;
#endif
typedef float FloatVec __attribute__((vector_size(4 * kWidth)));
typedef uint32_t WordVec __attribute__((vector_size(4 * kWidth)));
typedef uint16_t HalfVec __attribute__((vector_size(2 * kWidth)));
typedef int32_t IntVec __attribute__((vector_size(4 * kWidth)));

inline FloatVec load_vec(const float* p) {
    FloatVec v;
    std::memcpy(&v, p, sizeof v);
    return v;
}
inline FloatVec load_vec(const uint16_t* p) {  // bfloat16 -> float32: the bits go to the high half
    HalfVec h;
    std::memcpy(&h, p, sizeof h);
    return reinterpret_cast<FloatVec>(__builtin_convertvector(h, WordVec) << 16);
}
inline WordVec rounded_bits(FloatVec v) {  // the bfloat16 of v in the high half (nearest even; NaN stays NaN)
    const WordVec u = reinterpret_cast<WordVec>(v);
    const WordVec nan = (u & 0x7fffffffu) > 0x7f800000u;
    return ((u + 0x7fffu + ((u >> 16) & 1u)) & ~nan) | (0x7fc00000u & nan);
}
inline float horizontal_sum(FloatVec v) {  // pairwise: lanes i and i + kWidth/2, then halves again
    float lanes[kWidth];
    std::memcpy(lanes, &v, sizeof v);
    for (int n = kWidth / 2; n > 0; n /= 2)
        for (int i = 0; i < n; ++i) lanes[i] += lanes[i + n];
    return lanes[0];
}
inline void store_vec(float* p, FloatVec v) { std::memcpy(p, &v, sizeof v); }
inline void store_vec(uint16_t* p, FloatVec v) {  // round to nearest even; NaN stays NaN
#if defined(__AVX512BF16__)
    const __m256bh h = _mm512_cvtneps_pbh(reinterpret_cast<__m512>(v));  // one instruction, same rounding
    std::memcpy(p, &h, sizeof h);
#else
    const HalfVec h = __builtin_convertvector(rounded_bits(v) >> 16, HalfVec);
    std::memcpy(p, &h, sizeof h);
#endif
}

// bfloat16 pairs: one vector load holds 2*kWidth channels as kWidth words (channel 2i low, 2i + 1
// high). Their float32 values are the words shifted up (even channels) and masked (odd channels): one
// load and two integer ops, where widening kWidth values at a time costs a slow cross-lane op per load.
inline WordVec load_pairs(const uint16_t* p) {
    WordVec u;
    std::memcpy(&u, p, sizeof u);
    return u;
}
inline FloatVec even_channels(WordVec u) { return reinterpret_cast<FloatVec>(u << 16); }
inline FloatVec odd_channels(WordVec u) { return reinterpret_cast<FloatVec>(u & 0xffff0000u); }
inline void store_pairs(uint16_t* p, FloatVec even, FloatVec odd) {  // back to channel order
#if defined(__AVX512BF16__) && defined(__AVX512BW__)  // kWidth is 16 there
    // one rounding instruction for both halves (even channels low, odd high), one 16-bit interleave
    static const __m512i kInterleave = _mm512_set_epi16(31, 15, 30, 14, 29, 13, 28, 12, 27, 11, 26, 10, 25, 9, 24, 8,
                                                        23, 7, 22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0);
    const __m512i halves = reinterpret_cast<__m512i>(
        _mm512_cvtne2ps_pbh(reinterpret_cast<__m512>(odd), reinterpret_cast<__m512>(even)));
    const __m512i packed = _mm512_permutexvar_epi16(kInterleave, halves);
#else
    const WordVec packed = (rounded_bits(odd) & 0xffff0000u) | (rounded_bits(even) >> 16);
#endif
    std::memcpy(p, &packed, sizeof packed);
}

constexpr int kLanes = kWidth;  // pixels whose sample positions are computed together (one vector each)

// Bilinear samples of one tap for up to kLanes consecutive pixels of a row, computed lane-parallel
// (the loop below vectorizes): corner weights (mask folded in) and the top-left corner's pixel index,
// with `inside` bit j set when corner j (00, 01, 10, 11) lies in the image. Positions are clamped to
// [-1, H] x [-1, W]; a NaN position gets NaN weights and no corner inside, so its columns are NaN.
struct TapSamples {
    float w[4][kLanes];
    int32_t index[kLanes];
    int32_t inside[kLanes];
};

inline void tap_samples(const float* dy, const float* dx, const float* m, float row, float col0, int64_t H,
                        int64_t W, TapSamples& s) {
    FloatVec lane;
    for (int i = 0; i < kLanes; ++i) lane[i] = static_cast<float>(i);
    const FloatVec top = FloatVec{} + static_cast<float>(H), right = FloatVec{} + static_cast<float>(W);
    const FloatVec low = FloatVec{} - 1.f, zero = {};
    FloatVec py = row + load_vec(dy), px = col0 + lane + load_vec(dx);
    const IntVec nan = (py != py) | (px != px);  // all ones where NaN
    py = nan ? zero : (py < low ? low : (py > top ? top : py));
    px = nan ? zero : (px < low ? low : (px > right ? right : px));
    // floor: truncate, then step down where that rounded a negative value up
    IntVec y0 = __builtin_convertvector(py, IntVec), x0 = __builtin_convertvector(px, IntVec);
    y0 += __builtin_convertvector(y0, FloatVec) > py;  // true is -1
    x0 += __builtin_convertvector(x0, FloatVec) > px;
    const FloatVec fy = py - __builtin_convertvector(y0, FloatVec), fx = px - __builtin_convertvector(x0, FloatVec);
    const FloatVec scale = nan ? zero + NAN : load_vec(m);
    const FloatVec w[4] = {(1 - fy) * (1 - fx) * scale, (1 - fy) * fx * scale, fy * (1 - fx) * scale, fy * fx * scale};
    const IntVec index = y0 * static_cast<int32_t>(W) + x0;
    // y0 is in [-1, H], so the top row is inside when 0 <= y0 < H and the bottom one when y0 + 1 < H
    const int32_t h = static_cast<int32_t>(H), wd = static_cast<int32_t>(W);
    const IntVec top_in = (y0 >= 0) & (y0 < h), bottom_in = y0 + 1 < h;
    const IntVec left_in = (x0 >= 0) & (x0 < wd), right_in = x0 + 1 < wd;
    const IntVec inside = ~nan & (((top_in & left_in) & 1) | ((top_in & right_in) & 2) | ((bottom_in & left_in) & 4) |
                                  ((bottom_in & right_in) & 8));
    for (int j = 0; j < 4; ++j) std::memcpy(s.w[j], &w[j], sizeof w[j]);
    std::memcpy(s.index, &index, sizeof index);
    std::memcpy(s.inside, &inside, sizeof inside);
}

// Columns of output pixels [begin, end) of the strip (pixel p = (b*rows + r - row0)*out_w + c), in
// groups of up to kLanes pixels of one row: per tap, the positions lane-parallel (tap_samples), then
// per pixel the 4-corner sum. kC (a multiple of 16) fixes the channel count at compile time: that sum
// is then a few vector registers with no loop-carried dependency, so pixels overlap in the pipeline;
// kC = 0 is the scalar loop for any channel count. Corners outside the image read a zero row (never
// a border pixel with weight 0: a NaN or Inf there must not leak in).
template <int kC, typename TIn, typename TOut>
void columns(const TIn* x, int64_t channels, const View& offset, const View* mask, const Geometry& g, TOut* cols,
             int64_t row0, int64_t rows, int64_t begin, int64_t end) {
    static const TIn kZeros[1024] = {};
    const int64_t C = kC > 0 ? kC : channels;
    const int64_t H = g.in_h, W = g.in_w;
    float dy[kLanes] = {}, dx[kLanes] = {}, m[kLanes];
    std::fill(m, m + kLanes, 1.f);
    TapSamples s;
    for (int64_t p = begin; p < end;) {
        const int64_t c0 = p % g.out_w, b = p / g.out_w / rows, r = row0 + p / g.out_w % rows;
        const int64_t n = std::min<int64_t>({kLanes, g.out_w - c0, end - p});
        const TIn* image = x + b * H * W * C;
        for (int64_t k = 0; k < g.taps; ++k) {
            offset.run(b, 2 * k, r, c0, n, dy);
            offset.run(b, 2 * k + 1, r, c0, n, dx);
            if (mask) mask->run(b, k, r, c0, n, m);
            tap_samples(dy, dx, m, static_cast<float>(r + g.tap_y[k]), static_cast<float>(c0 + g.tap_x[k]), H, W, s);
            for (int64_t i = 0; i < n; ++i) {
                TOut* col = cols + (p + i) * g.taps * C + k * C;
                const float w00 = s.w[0][i], w01 = s.w[1][i], w10 = s.w[2][i], w11 = s.w[3][i];
                const TIn* corner = image + static_cast<int64_t>(s.index[i]) * C;
                const int32_t inside = s.inside[i];
                const TIn* v00 = inside & 1 ? corner : kZeros;
                const TIn* v01 = inside & 2 ? corner + C : kZeros;
                const TIn* v10 = inside & 4 ? corner + W * C : kZeros;
                const TIn* v11 = inside & 8 ? corner + (W + 1) * C : kZeros;
                if constexpr (kC % (2 * kWidth) == 0 && kC > 0 && sizeof(TIn) == 2 && sizeof(TOut) == 2) {
                    for (int64_t ch = 0; ch < kC; ch += 2 * kWidth) {
                        const WordVec a = load_pairs(v00 + ch), bb = load_pairs(v01 + ch);
                        const WordVec cc = load_pairs(v10 + ch), d = load_pairs(v11 + ch);
                        store_pairs(col + ch,
                                    (w00 * even_channels(a) + w01 * even_channels(bb)) +
                                        (w10 * even_channels(cc) + w11 * even_channels(d)),
                                    (w00 * odd_channels(a) + w01 * odd_channels(bb)) +
                                        (w10 * odd_channels(cc) + w11 * odd_channels(d)));
                    }
                } else if constexpr (kC > 0) {
                    for (int64_t ch = 0; ch < kC; ch += kWidth)
                        store_vec(col + ch, (w00 * load_vec(v00 + ch) + w01 * load_vec(v01 + ch)) +
                                          (w10 * load_vec(v10 + ch) + w11 * load_vec(v11 + ch)));
                } else {
                    for (int64_t ch = 0; ch < C; ++ch)
                        store(col + ch, (w00 * to_float(v00[ch]) + w01 * to_float(v01[ch])) +
                                        (w10 * to_float(v10[ch]) + w11 * to_float(v11[ch])));
                }
            }
        }
        p += n;
    }
}

// Gradients for images [b_begin, b_end) (see deform_columns_backward). One thread owns an image, so its
// grad_x rows are written by that thread only. Corners outside the image read a zero row and write
// their (weight x gradient) to a scratch row that is thrown away: no branch in the channel loops.
template <int kC>
void columns_backward(const float* x, int64_t channels, const float* offset, const float* mask, const Geometry& g,
                      int64_t out_h, const float* grad_cols, float* grad_x, float* grad_offset, float* grad_mask,
                      int64_t b_begin, int64_t b_end) {
    static const float kZeros[1024] = {};
    float sink[1024];
    const int64_t C = kC > 0 ? kC : channels;
    const int64_t H = g.in_h, W = g.in_w, K = g.taps, plane = out_h * g.out_w;
    for (int64_t b = b_begin; b < b_end; ++b) {
        const float* image = x + b * H * W * C;
        float* grad_image = grad_x + b * H * W * C;
        for (int64_t r = 0; r < out_h; ++r) {
            for (int64_t c = 0; c < g.out_w; ++c) {
                const int64_t pix = r * g.out_w + c, p = b * plane + pix;
                for (int64_t k = 0; k < K; ++k) {
                    const int64_t oy = (b * 2 * K + 2 * k) * plane + pix, ox = oy + plane, om = (b * K + k) * plane + pix;
                    const float py = static_cast<float>(r + g.tap_y[k]) + offset[oy];
                    const float px = static_cast<float>(c + g.tap_x[k]) + offset[ox];
                    if (py != py || px != px) {
                        grad_offset[oy] = grad_offset[ox] = NAN;
                        if (mask) grad_mask[om] = NAN;
                        continue;
                    }
                    const bool clamped_y = py < -1.f || py > static_cast<float>(H);
                    const bool clamped_x = px < -1.f || px > static_cast<float>(W);
                    const float cy = std::min(std::max(py, -1.f), static_cast<float>(H));
                    const float cx = std::min(std::max(px, -1.f), static_cast<float>(W));
                    const int64_t y0 = static_cast<int64_t>(std::floor(cy)), x0 = static_cast<int64_t>(std::floor(cx));
                    const float fy = cy - static_cast<float>(y0), fx = cx - static_cast<float>(x0);
                    const float m = mask ? mask[om] : 1.f;
                    const bool top = y0 >= 0 && y0 < H, bottom = y0 + 1 >= 0 && y0 + 1 < H;
                    const bool left = x0 >= 0 && x0 < W, right = x0 + 1 >= 0 && x0 + 1 < W;
                    const int64_t i00 = (y0 * W + x0) * C;
                    const float* v00 = top && left ? image + i00 : kZeros;
                    const float* v01 = top && right ? image + i00 + C : kZeros;
                    const float* v10 = bottom && left ? image + i00 + W * C : kZeros;
                    const float* v11 = bottom && right ? image + i00 + (W + 1) * C : kZeros;
                    float* g00 = top && left ? grad_image + i00 : sink;
                    float* g01 = top && right ? grad_image + i00 + C : sink;
                    float* g10 = bottom && left ? grad_image + i00 + W * C : sink;
                    float* g11 = bottom && right ? grad_image + i00 + (W + 1) * C : sink;
                    const float w00 = (1 - fy) * (1 - fx), w01 = (1 - fy) * fx, w10 = fy * (1 - fx), w11 = fy * fx;
                    const float* gc = grad_cols + (p * K + k) * C;
                    float sum_y = 0.f, sum_x = 0.f, sum_m = 0.f;
                    if constexpr (kC > 0) {  // kWidth channels at a time; the three sums as vectors
                        FloatVec vy = {}, vx = {}, vm = {};
                        for (int64_t ch = 0; ch < kC; ch += kWidth) {
                            const FloatVec gv = load_vec(gc + ch), a = load_vec(v00 + ch), bb = load_vec(v01 + ch);
                            const FloatVec cc = load_vec(v10 + ch), d = load_vec(v11 + ch);
                            vm += gv * ((w00 * a + w01 * bb) + (w10 * cc + w11 * d));
                            vy += gv * ((1 - fx) * (cc - a) + fx * (d - bb));
                            vx += gv * ((1 - fy) * (bb - a) + fy * (d - cc));
                            const FloatVec mg = m * gv;
                            // one corner after the other: corners outside the image share the sink row
                            store_vec(g00 + ch, load_vec(g00 + ch) + w00 * mg);
                            store_vec(g01 + ch, load_vec(g01 + ch) + w01 * mg);
                            store_vec(g10 + ch, load_vec(g10 + ch) + w10 * mg);
                            store_vec(g11 + ch, load_vec(g11 + ch) + w11 * mg);
                        }
                        sum_y = horizontal_sum(vy), sum_x = horizontal_sum(vx), sum_m = horizontal_sum(vm);
                    } else for (int64_t ch = 0; ch < C; ++ch) {
                        const float gv = gc[ch], a = v00[ch], bb = v01[ch], cc = v10[ch], d = v11[ch];
                        sum_m += gv * (w00 * a + w01 * bb + w10 * cc + w11 * d);
                        sum_y += gv * ((1 - fx) * (cc - a) + fx * (d - bb));
                        sum_x += gv * ((1 - fy) * (bb - a) + fy * (d - cc));
                        const float mg = m * gv;
                        g00[ch] += w00 * mg;
                        g01[ch] += w01 * mg;
                        g10[ch] += w10 * mg;
                        g11[ch] += w11 * mg;
                    }
                    grad_offset[oy] = clamped_y ? 0.f : m * sum_y;
                    grad_offset[ox] = clamped_x ? 0.f : m * sum_x;
                    if (mask) grad_mask[om] = sum_m;
                }
            }
        }
    }
}

template <typename TIn, typename TOut>
void columns_dispatch(const void* x, int64_t channels, const View& offset, const View* mask, const Geometry& g,
                      void* cols, int64_t row0, int64_t rows, int64_t batch, int32_t threads) {
    const auto* in = static_cast<const TIn*>(x);
    auto* out = static_cast<TOut*>(cols);
    parallel_for(batch * rows * g.out_w, threads, [&](int64_t begin, int64_t end) {
        switch (channels) {  // the channel counts of the networks here, then a generic loop
            case 16: columns<16>(in, channels, offset, mask, g, out, row0, rows, begin, end); break;
            case 32: columns<32>(in, channels, offset, mask, g, out, row0, rows, begin, end); break;
            case 64: columns<64>(in, channels, offset, mask, g, out, row0, rows, begin, end); break;
            default: columns<0>(in, channels, offset, mask, g, out, row0, rows, begin, end);
        }
    });
}

// out[p] = x[p] * (1 + gamma) + beta (then ReLU when relu), gamma|beta = bias + cond[p] . weight, for
// pixels [begin, end). weight is (cond_channels, 2*kC): gamma's columns then beta's. gamma and beta of
// one pixel stay in vector registers. Only kC = 16, 32, 64: for other widths eager PyTorch's blocked
// 1x1 conv beats a per-pixel loop (measured 0.35-0.95x at 35 channels), so cfm.py keeps them eager.
template <int kC, typename T>
void cfm_pixels(const T* x, const T* cond, const float* weight, const float* bias, T* out, int64_t cond_channels,
                bool relu, int64_t begin, int64_t end) {
    constexpr int kVecs = 2 * kC / kWidth;
    for (int64_t p = begin; p < end; ++p) {
        const T* cp = cond + p * cond_channels;
        FloatVec acc[kVecs];
        for (int v = 0; v < kVecs; ++v) acc[v] = load_vec(bias + kWidth * v);
        for (int64_t j = 0; j < cond_channels; ++j) {
            const float cj = to_float(cp[j]);
            const float* row = weight + j * 2 * kC;
            for (int v = 0; v < kVecs; ++v) acc[v] += cj * load_vec(row + kWidth * v);
        }
        for (int v = 0; v < kVecs / 2; ++v) {
            FloatVec y = load_vec(x + p * kC + kWidth * v) * (1 + acc[v]) + acc[kVecs / 2 + v];
            if (relu) y = y <= 0 ? FloatVec{} : y;  // NaN stays NaN, as in torch's relu
            store_vec(out + p * kC + kWidth * v, y);
        }
    }
}

template <typename T>
int32_t cfm_dispatch(const void* x, const void* cond, const float* weight, const float* bias, void* out,
                     int64_t pixels, int64_t channels, int64_t cond_channels, bool relu, int32_t threads) {
    if (channels != 16 && channels != 32 && channels != 64) return -1;
    const auto* xs = static_cast<const T*>(x);
    const auto* cs = static_cast<const T*>(cond);
    auto* os = static_cast<T*>(out);
    parallel_for(pixels, threads, [&](int64_t begin, int64_t end) {
        switch (channels) {
            case 16: cfm_pixels<16>(xs, cs, weight, bias, os, cond_channels, relu, begin, end); break;
            case 32: cfm_pixels<32>(xs, cs, weight, bias, os, cond_channels, relu, begin, end); break;
            default: cfm_pixels<64>(xs, cs, weight, bias, os, cond_channels, relu, begin, end);
        }
    });
    return 0;
}

}  // namespace

extern "C" {

// out (pixels, channels) = CFM of x (pixels, channels) by cond (pixels, cond_channels), all contiguous
// (channels-last images) of one dtype; weight (cond_channels, 2*channels) and bias (2*channels) float32,
// gamma's then beta's. relu != 0 applies ReLU after. Returns 0, or -1 unless channels is 16, 32 or 64.
int32_t cfm_affine(const void* x, const void* cond, int32_t dtype, int64_t pixels, int64_t channels,
                   int64_t cond_channels, const float* weight, const float* bias, int32_t relu, void* out,
                   int32_t threads) {
    return dtype == kBFloat16
               ? cfm_dispatch<uint16_t>(x, cond, weight, bias, out, pixels, channels, cond_channels, relu != 0, threads)
               : cfm_dispatch<float>(x, cond, weight, bias, out, pixels, channels, cond_channels, relu != 0, threads);
}


// cols (batch*rows*out_w, taps*channels), contiguous, for output rows row0..row0+rows-1 of
// x (batch, in_h, in_w, channels) contiguous (channels-last). offset (batch, 2*taps, out_h, out_w) and
// mask (batch, taps, out_h, out_w) come with element strides; mask may be null. Returns 0; -1 when
// channels is above what the generic loop holds (1024); -2 when a frame has 2^31 pixels or more.
int32_t deform_columns(const void* x, int32_t x_dtype, int64_t channels, int64_t batch, int64_t in_h, int64_t in_w,
                       const void* offset, int32_t offset_dtype, const int64_t* offset_strides,
                       const void* mask, int32_t mask_dtype, const int64_t* mask_strides,
                       void* cols, int32_t cols_dtype, int64_t row0, int64_t rows, int64_t out_w,
                       int64_t taps, const int64_t* tap_y, const int64_t* tap_x, int32_t threads) {
    if (channels > 1024) return -1;
    if ((in_h + 1) * (in_w + 2) >= (int64_t{1} << 31)) return -2;  // pixel indices are int32
    const View off{offset, offset_dtype, offset_strides[0], offset_strides[1], offset_strides[2], offset_strides[3]};
    View mask_view{mask, mask_dtype, 0, 0, 0, 0};
    if (mask) mask_view = View{mask, mask_dtype, mask_strides[0], mask_strides[1], mask_strides[2], mask_strides[3]};
    const View* m = mask ? &mask_view : nullptr;
    const Geometry g{in_h, in_w, out_w, taps, tap_y, tap_x};
    if (x_dtype == kBFloat16 && cols_dtype == kBFloat16)
        columns_dispatch<uint16_t, uint16_t>(x, channels, off, m, g, cols, row0, rows, batch, threads);
    else if (x_dtype == kBFloat16)
        columns_dispatch<uint16_t, float>(x, channels, off, m, g, cols, row0, rows, batch, threads);
    else if (cols_dtype == kBFloat16)
        columns_dispatch<float, uint16_t>(x, channels, off, m, g, cols, row0, rows, batch, threads);
    else
        columns_dispatch<float, float>(x, channels, off, m, g, cols, row0, rows, batch, threads);
    return 0;
}

// The gradients of deform_columns over all out_h rows, float32: x (batch, in_h, in_w, channels) and
// grad_cols (batch*out_h*out_w, taps*channels) contiguous; offset (batch, 2*taps, out_h, out_w) and
// mask (batch, taps, out_h, out_w; may be null) contiguous. grad_x (like x, zeroed by the caller) is
// accumulated; grad_offset and grad_mask (like offset and mask) are written. Returns 0; -1 when
// channels is above 1024.
int32_t deform_columns_backward(const float* x, int64_t channels, int64_t batch, int64_t in_h, int64_t in_w,
                                const float* offset, const float* mask, const float* grad_cols, int64_t out_h,
                                int64_t out_w, int64_t taps, const int64_t* tap_y, const int64_t* tap_x,
                                float* grad_x, float* grad_offset, float* grad_mask, int32_t threads) {
    if (channels > 1024) return -1;
    const Geometry g{in_h, in_w, out_w, taps, tap_y, tap_x};
    parallel_for(batch, threads, [&](int64_t begin, int64_t end) {
        switch (channels) {
            case 16: columns_backward<16>(x, channels, offset, mask, g, out_h, grad_cols, grad_x, grad_offset, grad_mask, begin, end); break;
            case 32: columns_backward<32>(x, channels, offset, mask, g, out_h, grad_cols, grad_x, grad_offset, grad_mask, begin, end); break;
            case 64: columns_backward<64>(x, channels, offset, mask, g, out_h, grad_cols, grad_x, grad_offset, grad_mask, begin, end); break;
            default: columns_backward<0>(x, channels, offset, mask, g, out_h, grad_cols, grad_x, grad_offset, grad_mask, begin, end);
        }
    });
    return 0;
}

}  // extern "C"
