/* The azimuth FFT (paper: the azimuth FFT/IFFT stages between eqs. 9 and 17) along axis 0 of a row-major
 * complex64 (n, n_cols) array, for power-of-two n and any n_cols: a Stockham autosort FFT, one radix-R pass per
 * launch, ping-ponging between two buffers.
 *
 * Why not only VkFFT: on a CPU runtime (PoCL) VkFFT's GPU-shaped work-groups, local memory and barriers run
 * about 3x slower than this layout. Work item (c, b) does one radix-R butterfly for FFT_LANES neighbouring
 * columns (c FFT_LANES ...), held as split real and imaginary vectors (`cv`): the butterflies are then plain
 * vector arithmetic, which every runtime vectorises, and neighbouring work items read contiguous memory
 * (coalesced on GPUs). FFT_LANES (4, 8 or 16, `-D` from the host, uwbcl.focus.device_fft.fft_defines) follows the
 * device's preferred float vector width: on an AVX-512 CPU 16 lanes run a 1024 x 128 transform 2.2x faster than
 * 4 (PoCL, one thread). Lanes past n_cols read zero and are not written. docs/opencl.md has the measurements.
 *
 * Pass with sub-transform size ns (1, R1, R1 R2, ...; Govindaraju et al., SC 2008): butterfly b reads
 * x[b + r n/R], multiplies by the twiddle exp(-2 pi i r (b mod ns) / (ns R)) (from a host table of
 * exp(-2 pi i k / n)), does a length-R DFT and writes y[(b div ns) ns R + b mod ns + r ns]. The inverse
 * transform is conj(FFT(conj(x))), pass by pass; `scale` (1/n on the inverse's last pass, 1 otherwise) gives
 * numpy's normalisation. */

/* The host defines FFT_LANES (its value) and one of FFT_LANES_4, FFT_LANES_8, FFT_LANES_16 (for #ifdef). */
#ifndef FFT_LANES
#error "build with -DFFT_LANES=n -DFFT_LANES_n, n = 4, 8 or 16 (uwbcl.focus.device_fft.fft_defines)"
#endif
#ifdef FFT_LANES_16
typedef float16 lane_t;
#define VLOAD_LANES vload16
#define VSTORE_LANES vstore16
#else
#ifdef FFT_LANES_8
typedef float8 lane_t;
#define VLOAD_LANES vload8
#define VSTORE_LANES vstore8
#else
typedef float4 lane_t;
#define VLOAD_LANES vload4
#define VSTORE_LANES vstore4
#endif
#endif

/* FFT_LANES neighbouring complex samples as split real and imaginary parts. */
typedef struct {
    lane_t re, im;
} cv;

/* Samples col..col+FFT_LANES-1 of a row (p points at col); lanes at or past n_cols read zero. */
inline cv cv_load(__global const float2 *p, const int col, const int n_cols, const int conjugate) {
    cv a;
    if (col + FFT_LANES <= n_cols) {
        const __global float *f = (__global const float *)p;
#ifdef FFT_LANES_16
        const float16 v0 = vload16(0, f), v1 = vload16(1, f);
        a.re = (float16)(v0.even, v1.even);
        a.im = (float16)(v0.odd, v1.odd);
#else
#ifdef FFT_LANES_8
        const float16 v = vload16(0, f);
#else
        const float8 v = vload8(0, f);
#endif
        a.re = v.even;
        a.im = v.odd;
#endif
    } else {
        float re[FFT_LANES], im[FFT_LANES];
        for (int l = 0; l < FFT_LANES; ++l) {
            const float2 z = col + l < n_cols ? p[l] : (float2)(0.0f, 0.0f);
            re[l] = z.x;
            im[l] = z.y;
        }
        a.re = VLOAD_LANES(0, re);
        a.im = VLOAD_LANES(0, im);
    }
    if (conjugate)
        a.im = -a.im;
    return a;
}

inline void cv_store(__global float2 *p, const int col, const int n_cols, const cv a, const int conjugate,
                     const float scale) {
    const lane_t re = a.re * scale, im = (conjugate ? -a.im : a.im) * scale;
    if (col + FFT_LANES <= n_cols) {
        __global float *f = (__global float *)p;
#ifdef FFT_LANES_16
        const uint16 mask = (uint16)(0, 8, 1, 9, 2, 10, 3, 11, 4, 12, 5, 13, 6, 14, 7, 15);
        vstore16(shuffle2(re.lo, im.lo, mask), 0, f);
        vstore16(shuffle2(re.hi, im.hi, mask), 1, f);
#else
#ifdef FFT_LANES_8
        vstore16(shuffle2(re, im, (uint16)(0, 8, 1, 9, 2, 10, 3, 11, 4, 12, 5, 13, 6, 14, 7, 15)), 0, f);
#else
        vstore8(shuffle2(re, im, (uint8)(0, 4, 1, 5, 2, 6, 3, 7)), 0, f);
#endif
#endif
        return;
    }
    float r[FFT_LANES], i[FFT_LANES];
    VSTORE_LANES(re, 0, r);
    VSTORE_LANES(im, 0, i);
    for (int l = 0; l < FFT_LANES && col + l < n_cols; ++l)
        p[l] = (float2)(r[l], i[l]);
}

inline cv cv_add(const cv a, const cv b) {
    cv r = {a.re + b.re, a.im + b.im};
    return r;
}

inline cv cv_sub(const cv a, const cv b) {
    cv r = {a.re - b.re, a.im - b.im};
    return r;
}

/* a * w for one complex w (a twiddle shared by the lanes' columns) */
inline cv cv_twiddle(const cv a, const float2 w) {
    cv r = {a.re * w.x - a.im * w.y, a.re * w.y + a.im * w.x};
    return r;
}

/* -i a: the forward DFT's quarter turn */
inline cv cv_mul_minus_i(const cv a) {
    cv r = {a.im, -a.re};
    return r;
}

/* length-2 and length-4 DFTs in place, natural order */
inline void dft2(cv *a, cv *b) {
    const cv t = *a;
    *a = cv_add(t, *b);
    *b = cv_sub(t, *b);
}

inline void dft4(cv *v0, cv *v1, cv *v2, cv *v3) {
    const cv t0 = cv_add(*v0, *v2), t1 = cv_sub(*v0, *v2), t2 = cv_add(*v1, *v3);
    const cv t3 = cv_mul_minus_i(cv_sub(*v1, *v3));
    *v0 = cv_add(t0, t2);
    *v2 = cv_sub(t0, t2);
    *v1 = cv_add(t1, t3);
    *v3 = cv_sub(t1, t3);
}

#define FFT_LOAD(R)                                                                                           \
    const int col = FFT_LANES * get_global_id(0), b = get_global_id(1);                                       \
    if (col >= n_cols) return;                                                                                \
    const int stride = n / R, k = b % ns;                                                                     \
    cv v[R];                                                                                                  \
    for (int r = 0; r < R; ++r) {                                                                             \
        const cv a = cv_load(x + (b + r * stride) * n_cols + col, col, n_cols, inverse);                      \
        v[r] = r == 0 ? a : cv_twiddle(a, twiddle[r * k * (n / (ns * R))]);                                   \
    }

#define FFT_STORE(R)                                                                                          \
    const int out = (b / ns) * ns * R + k;                                                                    \
    for (int r = 0; r < R; ++r)                                                                               \
        cv_store(y + (out + r * ns) * n_cols + col, col, n_cols, v[r], inverse, scale);

__kernel void azimuth_fft_radix2(__global const float2 *restrict x, __global float2 *restrict y,
                                 __global const float2 *restrict twiddle, const int n, const int n_cols,
                                 const int ns, const int inverse, const float scale) {
    FFT_LOAD(2)
    dft2(&v[0], &v[1]);
    FFT_STORE(2)
}

__kernel void azimuth_fft_radix4(__global const float2 *restrict x, __global float2 *restrict y,
                                 __global const float2 *restrict twiddle, const int n, const int n_cols,
                                 const int ns, const int inverse, const float scale) {
    FFT_LOAD(4)
    dft4(&v[0], &v[1], &v[2], &v[3]);
    FFT_STORE(4)
}

__kernel void azimuth_fft_radix8(__global const float2 *restrict x, __global float2 *restrict y,
                                 __global const float2 *restrict twiddle, const int n, const int n_cols,
                                 const int ns, const int inverse, const float scale) {
    FFT_LOAD(8)
    /* even and odd halves, then combine with exp(-2 pi i k / 8) */
    dft4(&v[0], &v[2], &v[4], &v[6]);
    dft4(&v[1], &v[3], &v[5], &v[7]);
    const float h = 0.70710678118654752440f;
    const cv o1 = {h * (v[3].re + v[3].im), h * (v[3].im - v[3].re)};    /* W8^1 O[1] */
    const cv o2 = cv_mul_minus_i(v[5]);                                   /* W8^2 O[2] */
    const cv o3 = {h * (v[7].im - v[7].re), -h * (v[7].re + v[7].im)};   /* W8^3 O[3] */
    const cv e0 = v[0], e1 = v[2], e2 = v[4], e3 = v[6], o0 = v[1];
    v[0] = cv_add(e0, o0);
    v[4] = cv_sub(e0, o0);
    v[1] = cv_add(e1, o1);
    v[5] = cv_sub(e1, o1);
    v[2] = cv_add(e2, o2);
    v[6] = cv_sub(e2, o2);
    v[3] = cv_add(e3, o3);
    v[7] = cv_sub(e3, o3);
    FFT_STORE(8)
}
