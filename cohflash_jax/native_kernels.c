/* A sub-tile's I/Q half in one pass over its frames (cohflash_jax/native.py).

   frames (4, n, p) uint16, pixels contiguous, frame rows `row_stride` and CCD planes
   `plane_stride` elements apart (a sub-tile cut from a wider tile is read in place). For each
   pixel: each CCD's highest and lowest value, and the second moments of I and Q = W·x + b,
   summed in float32 over blocks of BLOCK_FRAMES frames
   and in float64 across blocks; from them the carrier axis (cos φ, sin φ), the orthogonal
   variance and the total variance, as reconstruct/programs.py's `axis_and_checks` computes
   them; then, reading the frames again (from cache), the rotated sequence
   r = (W·x + b)·(cos φ, sin φ) (n, p) float32, as its `rotated_from_frames` does. The moments
   are centred, so the bias b cancels in them. XLA's CPU code makes ~60 MB of memory traffic of
   a sub-tile's 7.7 MB of frames (docs/performance.md); this reads them twice.

   The loops vectorise over pixels, in blocks of at most PIXEL_BLOCK that go through every frame
   (a block's accumulators stay in L1). The kernel is compiled for AVX2 and for the baseline ISA,
   and the caller chooses (it knows the ISA XLA is held to); an AVX-512 build ran slower than
   the AVX2 one (docs/performance.md). */

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#if defined(__unix__) || defined(__APPLE__)
#include <sys/types.h>
#include <sys/uio.h>
#define HAVE_PREADV 1
#endif

#define BLOCK_FRAMES 64 /* float32 partial sums over this many frames, then float64 */
#define UNROLL 2        /* frames a pixel's accumulators stay in registers for */
#define PREFETCH 8      /* frames ahead whose rows are asked for */
/* pixels a pass over every frame takes at most: a block's accumulators and weights stay in
   the L1 cache (~130 bytes a pixel); a sub-tile of a short sweep is thousands of pixels wide */
#define PIXEL_BLOCK 512

/* the loop after it has no dependence between iterations (its arrays' rows do not overlap) */
#if defined(__clang__)
#define INDEPENDENT_ITERATIONS _Pragma("clang loop vectorize(assume_safety)")
#elif defined(__GNUC__)
#define INDEPENDENT_ITERATIONS _Pragma("GCC ivdep")
#else
#define INDEPENDENT_ITERATIONS
#endif

enum { KERNEL_OK = 0, KERNEL_NO_MEMORY = 1, KERNEL_BAD_SHAPE = 2 };

/* the kernels' calling convention: cohflash_jax/native.py loads a library built for this one
   only (a library left from an older build is not called with the wrong arguments) */
int cohflash_kernel_abi(void) { return 2; }

typedef struct {
    uint16_t *restrict hi, *restrict lo;                       /* (4, p) each CCD's extremes */
    float *restrict part;                                      /* (5, p) float32 partial sums */
    double *restrict sums;                                     /* (5, p) Σi, Σq, Σi², Σq², Σiq */
    float *restrict w;                                         /* (8, p) the weights per pixel */
    float *restrict e;                                         /* (5, p) rotation weights, offset */
} Scratch;

/* the frames x[u·stride + k] (u < frames) into the extremes and partial sums, each pixel's
   accumulators in registers across the frames */
static inline __attribute__((always_inline)) void accumulate(const uint16_t *restrict x, int64_t plane, int64_t stride,
                                                              int64_t p, int frames, Scratch s)
{
    uint16_t *restrict hi = s.hi, *restrict lo = s.lo;
    float *restrict part = s.part;
    const float *restrict w = s.w;
    INDEPENDENT_ITERATIONS
    for (int64_t k = 0; k < p; k++) {
        uint16_t h0 = hi[k], h1 = hi[p + k], h2 = hi[2 * p + k], h3 = hi[3 * p + k];
        uint16_t l0 = lo[k], l1 = lo[p + k], l2 = lo[2 * p + k], l3 = lo[3 * p + k];
        float si = part[k], sq = part[p + k], sii = part[2 * p + k], sqq = part[3 * p + k], siq = part[4 * p + k];
        const float a00 = w[k], a01 = w[p + k], a02 = w[2 * p + k], a03 = w[3 * p + k];
        const float a10 = w[4 * p + k], a11 = w[5 * p + k], a12 = w[6 * p + k], a13 = w[7 * p + k];
        for (int u = 0; u < frames; u++) {
            const uint16_t x0 = x[u * stride + k], x1 = x[plane + u * stride + k];
            const uint16_t x2 = x[2 * plane + u * stride + k], x3 = x[3 * plane + u * stride + k];
            h0 = x0 > h0 ? x0 : h0;
            l0 = x0 < l0 ? x0 : l0;
            h1 = x1 > h1 ? x1 : h1;
            l1 = x1 < l1 ? x1 : l1;
            h2 = x2 > h2 ? x2 : h2;
            l2 = x2 < l2 ? x2 : l2;
            h3 = x3 > h3 ? x3 : h3;
            l3 = x3 < l3 ? x3 : l3;
            const float v0 = x0, v1 = x1, v2 = x2, v3 = x3;
            const float i = a00 * v0 + a01 * v1 + a02 * v2 + a03 * v3;
            const float q = a10 * v0 + a11 * v1 + a12 * v2 + a13 * v3;
            si += i;
            sq += q;
            sii += i * i;
            sqq += q * q;
            siq += i * q;
        }
        hi[k] = h0, hi[p + k] = h1, hi[2 * p + k] = h2, hi[3 * p + k] = h3;
        lo[k] = l0, lo[p + k] = l1, lo[2 * p + k] = l2, lo[3 * p + k] = l3;
        part[k] = si, part[p + k] = sq, part[2 * p + k] = sii, part[3 * p + k] = sqq, part[4 * p + k] = siq;
    }
}

static inline __attribute__((always_inline)) void
iq_half_body(const uint16_t *restrict frames, int64_t n, int64_t p, int64_t stride, int64_t plane, int64_t width,
             const float *restrict bias, double saturation,
             float *restrict r, float *restrict cos_phase, float *restrict sin_phase, double *restrict noise_var,
             double *restrict total_var, uint8_t *restrict dead, uint8_t *restrict saturated, Scratch s)
{
    for (int64_t k = 0; k < 4 * p; k++) s.hi[k] = 0, s.lo[k] = 0xffff;
    for (int64_t k = 0; k < 5 * p; k++) s.sums[k] = 0;
    for (int64_t m0 = 0; m0 < n; m0 += BLOCK_FRAMES) {
        const int64_t m1 = m0 + BLOCK_FRAMES < n ? m0 + BLOCK_FRAMES : n;
        for (int64_t k = 0; k < 5 * p; k++) s.part[k] = 0;
        int64_t m = m0;
        for (; m + UNROLL <= m1; m += UNROLL) {
            const uint16_t *x = frames + m * stride;
            if (m + PREFETCH + UNROLL <= n)
                for (int c = 0; c < 4; c++)
                    for (int u = 0; u < UNROLL; u++) {
                        const char *ahead = (const char *)(x + c * plane + (PREFETCH + u) * stride);
                        for (int64_t at = 0; at < (int64_t)(p * sizeof(uint16_t)); at += 64) __builtin_prefetch(ahead + at);
                    }
            accumulate(x, plane, stride, p, UNROLL, s);
        }
        for (; m < m1; m++) accumulate(frames + m * stride, plane, stride, p, 1, s);
        for (int64_t k = 0; k < 5 * p; k++) s.sums[k] += s.part[k];
    }
    const double frames_over_dof = (double)n / (n - 2 > 1 ? n - 2 : 1);
    for (int64_t k = 0; k < p; k++) {
        const double mi = s.sums[k] / n, mq = s.sums[p + k] / n;
        const double sii = s.sums[2 * p + k] / n - mi * mi, sqq = s.sums[3 * p + k] / n - mq * mq;
        const double siq = s.sums[4 * p + k] / n - mi * mq;
        /* φ = ½·atan2(2 siq, sii − sqq) without trigonometry (`estimate.iq.half_angle`); the
           squares stay far inside float64's range for 16-bit data, so no `hypot`, a libm call a
           pixel (docs/performance.md) */
        const double x = sii - sqq, y = 2 * siq, radius = sqrt(x * x + y * y);
        const double ax = x >= 0 ? radius + x : y, ay = x >= 0 ? y : radius - x, norm = sqrt(ax * ax + ay * ay);
        double c = norm > 0 ? ax / norm : 1, sn = norm > 0 ? ay / norm : 0;
        if (c < 0 || (c == 0 && sn < 0)) c = -c, sn = -sn;
        /* the mean term A·w_0, the bias included, comes out positive */
        if ((mi + bias[k]) * c + (mq + bias[width + k]) * sn < 0) c = -c, sn = -sn;
        const double orthogonal = sn * sn * sii + c * c * sqq - 2 * sn * c * siq;
        noise_var[k] = (orthogonal > 0 ? orthogonal : 0) * frames_over_dof;
        total_var[k] = sii + sqq > 0 ? sii + sqq : 0;
        cos_phase[k] = (float)c;
        sin_phase[k] = (float)sn;
        int is_dead = 0, is_saturated = 0;
        for (int ch = 0; ch < 4; ch++) {
            is_dead |= s.hi[ch * p + k] == s.lo[ch * p + k];
            is_saturated |= saturation >= 0 && s.hi[ch * p + k] >= saturation;
        }
        dead[k] = (uint8_t)is_dead;
        saturated[k] = (uint8_t)is_saturated;
    }
    /* r = (W·x + b)·(c, s) = x·Wᵀ(c, s) + b·(c, s) */
    float *restrict e = s.e;
    for (int ch = 0; ch < 4; ch++)
        for (int64_t k = 0; k < p; k++)
            e[ch * p + k] = s.w[ch * p + k] * cos_phase[k] + s.w[(4 + ch) * p + k] * sin_phase[k];
    for (int64_t k = 0; k < p; k++) e[4 * p + k] = bias[k] * cos_phase[k] + bias[width + k] * sin_phase[k];
    for (int64_t m = 0; m < n; m++) {
        const uint16_t *restrict x = frames + m * stride;
        float *restrict out = r + m * width;
        INDEPENDENT_ITERATIONS
        for (int64_t k = 0; k < p; k++)
            out[k] = e[k] * x[k] + e[p + k] * x[plane + k] + e[2 * p + k] * x[2 * plane + k] +
                     e[3 * p + k] * x[3 * plane + k] + e[4 * p + k];
    }
}

/* frames' rows `row_stride` and planes `plane_stride` elements apart; weights: (2, 4) uniform, or
   (2, 4, p) per pixel (`per_pixel`); bias (2, p); saturation < 0: none; r (n, p) contiguous */
#define DEFINE_KERNEL(NAME, TARGET)                                                                                    \
    TARGET int NAME(const uint16_t *frames, int64_t n, int64_t p, int64_t row_stride, int64_t plane_stride,            \
                    const float *weights, int64_t per_pixel,                                                           \
                    const float *bias, double saturation, float *r, float *cos_phase, float *sin_phase,                \
                    double *noise_var, double *total_var, uint8_t *dead, uint8_t *saturated)                            \
    {                                                                                                                  \
        if (n < 1 || p < 1 || row_stride < p || plane_stride < n * row_stride) return KERNEL_BAD_SHAPE;                 \
        /* blocks of at most PIXEL_BLOCK pixels, as even as vectors of 16 allow, each through   */ \
        /* every frame: r's and the bias's rows are `p` wide, the block's scratch its own width  */ \
        const int64_t blocks = (p + PIXEL_BLOCK - 1) / PIXEL_BLOCK;                                                    \
        int64_t block = ((p + blocks - 1) / blocks + 15) / 16 * 16;                                                    \
        block = block < p ? block : p;                                                                                 \
        uint16_t *extremes = malloc(8 * block * sizeof(uint16_t));                                                    \
        float *floats = malloc(18 * block * sizeof(float));                                                            \
        double *sums = malloc(5 * block * sizeof(double));                                                             \
        if (!extremes || !floats || !sums) {                                                                           \
            free(extremes), free(floats), free(sums);                                                                  \
            return KERNEL_NO_MEMORY;                                                                                   \
        }                                                                                                              \
        for (int64_t k0 = 0; k0 < p; k0 += block) {                                                                    \
            const int64_t b = p - k0 < block ? p - k0 : block;                                                         \
            Scratch s = {extremes, extremes + 4 * b, floats, sums, floats + 5 * b, floats + 13 * b};                   \
            for (int j = 0; j < 8; j++)                                                                                \
                for (int64_t k = 0; k < b; k++) s.w[j * b + k] = per_pixel ? weights[j * p + k0 + k] : weights[j];    \
            iq_half_body(frames + k0, n, b, row_stride, plane_stride, p, bias + k0, saturation, r + k0,                \
                         cos_phase + k0, sin_phase + k0, noise_var + k0, total_var + k0, dead + k0, saturated + k0, s); \
        }                                                                                                              \
        free(extremes), free(floats), free(sums);                                                                      \
        return KERNEL_OK;                                                                                              \
    }

#if (defined(__GNUC__) || defined(__clang__)) && defined(__x86_64__)
DEFINE_KERNEL(cohflash_iq_half_u16_avx2, __attribute__((target("avx2,fma"))))
int cohflash_has_x86_kernels(void) { return 1; }
#else
int cohflash_has_x86_kernels(void) { return 0; }
#endif
DEFINE_KERNEL(cohflash_iq_half_u16, )

/* Chunks of a capture file read straight into place, each with one preadv scattering it over
   `iovec_counts[i]` buffers from the struct iovec at `iovec_addresses[i]` (as
   cohflash_jax/chunk_reads.py lays them out): a whole tile in one call, without the
   interpreter between the reads (nor its lock taken back after each). Returns
   -1 where every chunk was read whole, else the index of the first that was not, its byte count
   in *got (negative: failed, errno kept). */
#ifdef HAVE_PREADV
int64_t cohflash_read_chunks(int fd, int64_t count, const int64_t *offsets, const int64_t *wants,
                             const uint64_t *iovec_addresses, const int32_t *iovec_counts, int64_t *got)
{
    for (int64_t i = 0; i < count; i++) {
        const struct iovec *iovecs = (const struct iovec *)(uintptr_t)iovec_addresses[i];
        const ssize_t read = preadv(fd, iovecs, iovec_counts[i], (off_t)offsets[i]);
        if (read != wants[i]) {
            *got = read;
            return i;
        }
    }
    return -1;
}
#endif
