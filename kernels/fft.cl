/* The azimuth FFT (paper: the azimuth FFT/IFFT stages between eqs. 9 and 17) along axis 0 of a row-major
 * complex64 (n, n_cols) array, for power-of-two n and n_cols a multiple of 4: a Stockham autosort FFT, one
 * radix-R pass per launch, ping-ponging between two buffers.
 *
 * Why not only VkFFT: on a CPU runtime (PoCL) VkFFT's GPU-shaped work-groups, local memory and barriers run
 * about 3x slower than this layout. Work item (c, b) does one radix-R butterfly for the four neighbouring
 * columns 4c..4c+3, held as split real and imaginary float4 (`c4`, common.cl): the butterflies are then plain float4
 * arithmetic, which every runtime vectorises, and neighbouring work items read contiguous memory (coalesced
 * on GPUs). docs/opencl.md has the measurements.
 *
 * Pass with sub-transform size ns (1, R1, R1 R2, ...; Govindaraju et al., SC 2008): butterfly b reads
 * x[b + r n/R], multiplies by the twiddle exp(-2 pi i r (b mod ns) / (ns R)) (from a host table of
 * exp(-2 pi i k / n)), does a length-R DFT and writes y[(b div ns) ns R + b mod ns + r ns]. The inverse
 * transform is conj(FFT(conj(x))), pass by pass; `scale` (1/n on the inverse's last pass, 1 otherwise) gives
 * numpy's normalisation. */

inline c4 c4_load(__global const float2 *p, const int conjugate) {
    const float8 v = vload8(0, (__global const float *)p);
    c4 a = {v.even, conjugate ? -v.odd : v.odd};
    return a;
}

inline void c4_store(__global float2 *p, const c4 a, const int conjugate, const float scale) {
    const float4 re = a.re * scale, im = (conjugate ? -a.im : a.im) * scale;
    vstore8((float8)(re.s0, im.s0, re.s1, im.s1, re.s2, im.s2, re.s3, im.s3), 0, (__global float *)p);
}

inline c4 c4_add(const c4 a, const c4 b) {
    c4 r = {a.re + b.re, a.im + b.im};
    return r;
}

inline c4 c4_sub(const c4 a, const c4 b) {
    c4 r = {a.re - b.re, a.im - b.im};
    return r;
}

/* a * w for one complex w (a twiddle shared by the four columns) */
inline c4 c4_twiddle(const c4 a, const float2 w) {
    c4 r = {a.re * w.x - a.im * w.y, a.re * w.y + a.im * w.x};
    return r;
}

/* -i a: the forward DFT's quarter turn */
inline c4 c4_mul_minus_i(const c4 a) {
    c4 r = {a.im, -a.re};
    return r;
}

/* length-2 and length-4 DFTs in place, natural order */
inline void dft2(c4 *a, c4 *b) {
    const c4 t = *a;
    *a = c4_add(t, *b);
    *b = c4_sub(t, *b);
}

inline void dft4(c4 *v0, c4 *v1, c4 *v2, c4 *v3) {
    const c4 t0 = c4_add(*v0, *v2), t1 = c4_sub(*v0, *v2), t2 = c4_add(*v1, *v3);
    const c4 t3 = c4_mul_minus_i(c4_sub(*v1, *v3));
    *v0 = c4_add(t0, t2);
    *v2 = c4_sub(t0, t2);
    *v1 = c4_add(t1, t3);
    *v3 = c4_sub(t1, t3);
}

#define FFT_LOAD(R)                                                                                          \
    const int col = 4 * get_global_id(0), b = get_global_id(1);                                              \
    if (col >= n_cols) return;                                                                               \
    const int stride = n / R, k = b % ns;                                                                    \
    c4 v[R];                                                                                                 \
    for (int r = 0; r < R; ++r) {                                                                            \
        const c4 a = c4_load(x + (b + r * stride) * n_cols + col, inverse);                                  \
        v[r] = r == 0 ? a : c4_twiddle(a, twiddle[r * k * (n / (ns * R))]);                                      \
    }

#define FFT_STORE(R)                                                                                         \
    const int out = (b / ns) * ns * R + k;                                                                   \
    for (int r = 0; r < R; ++r)                                                                              \
        c4_store(y + (out + r * ns) * n_cols + col, v[r], inverse, scale);

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
    const c4 o1 = {h * (v[3].re + v[3].im), h * (v[3].im - v[3].re)};    /* W8^1 O[1] */
    const c4 o2 = c4_mul_minus_i(v[5]);                                   /* W8^2 O[2] */
    const c4 o3 = {h * (v[7].im - v[7].re), -h * (v[7].re + v[7].im)};   /* W8^3 O[3] */
    const c4 e0 = v[0], e1 = v[2], e2 = v[4], e3 = v[6], o0 = v[1];
    v[0] = c4_add(e0, o0);
    v[4] = c4_sub(e0, o0);
    v[1] = c4_add(e1, o1);
    v[5] = c4_sub(e1, o1);
    v[2] = c4_add(e2, o2);
    v[6] = c4_sub(e2, o2);
    v[3] = c4_add(e3, o3);
    v[7] = c4_sub(e3, o3);
    FFT_STORE(8)
}
