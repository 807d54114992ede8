/* The azimuth FFT (paper: the azimuth FFT/IFFT stages between eqs. 9 and 17) along axis 0 of a row-major
 * (n, n_cols) array, for power-of-two n: a Stockham autosort FFT, one radix-R pass per launch, ping-ponging
 * between two buffers.
 *
 * Why not only VkFFT: on a CPU runtime (PoCL) VkFFT's GPU-shaped work-groups, local memory and barriers run
 * 2-3x slower than this layout, where work item (col, b) does one radix-R butterfly of column col and
 * neighbouring work items are neighbouring columns, i.e. contiguous memory: the runtime vectorises across
 * columns with no shuffles. On GPUs the same layout gives coalesced loads. docs/opencl.md has the measurements.
 *
 * Pass with sub-transform size ns (1, R1, R1 R2, ...; Govindaraju et al., SC 2008): butterfly b reads
 * x[b + r n/R], multiplies by the twiddle exp(-2 pi i r (b mod ns) / (ns R)) (from a host table of
 * exp(-2 pi i k / n) in the data precision), does a length-R DFT and writes y[(b div ns) ns R + b mod ns + r ns].
 * The inverse transform is conj(FFT(conj(x))), pass by pass; `scale` (1/n on the inverse's last pass, 1
 * otherwise) gives numpy's normalisation. complex64 only (cplx_t is float2 in the main program); complex128
 * transforms use VkFFT, faster there on PoCL. */

inline cplx_t conj_if(cplx_t v, const int inverse) {
    return inverse ? (cplx_t)(v.x, -v.y) : v;
}

/* -i v: the forward DFT's quarter turn */
inline cplx_t mul_minus_i(cplx_t v) {
    return (cplx_t)(v.y, -v.x);
}

#define FFT_LOAD(R)                                                                                          \
    const int col = get_global_id(0), b = get_global_id(1);                                                  \
    if (col >= n_cols) return;                                                                               \
    const int stride = n / R, k = b % ns;                                                                    \
    cplx_t v[R];                                                                                             \
    for (int r = 0; r < R; ++r) {                                                                            \
        const cplx_t a = conj_if(x[(b + r * stride) * n_cols + col], inverse);                               \
        v[r] = r == 0 ? a : cmul(a, twiddle[r * k * (n / (ns * R))]);                                        \
    }

#define FFT_STORE(R)                                                                                         \
    const int out = (b / ns) * ns * R + k;                                                                   \
    for (int r = 0; r < R; ++r)                                                                              \
        y[(out + r * ns) * n_cols + col] = conj_if(v[r], inverse) * scale;

inline void dft2(cplx_t *a, cplx_t *b) {
    const cplx_t t = *a;
    *a = t + *b;
    *b = t - *b;
}

/* length-4 DFT in place, natural order */
inline void dft4(cplx_t *v0, cplx_t *v1, cplx_t *v2, cplx_t *v3) {
    const cplx_t t0 = *v0 + *v2, t1 = *v0 - *v2, t2 = *v1 + *v3, t3 = mul_minus_i(*v1 - *v3);
    *v0 = t0 + t2;
    *v2 = t0 - t2;
    *v1 = t1 + t3;
    *v3 = t1 - t3;
}

__kernel void azimuth_fft_radix2(__global const cplx_t *restrict x, __global cplx_t *restrict y,
                                 __global const cplx_t *restrict twiddle, const int n, const int n_cols,
                                 const int ns, const int inverse, const cplx_real_t scale) {
    FFT_LOAD(2)
    dft2(&v[0], &v[1]);
    FFT_STORE(2)
}

__kernel void azimuth_fft_radix4(__global const cplx_t *restrict x, __global cplx_t *restrict y,
                                 __global const cplx_t *restrict twiddle, const int n, const int n_cols,
                                 const int ns, const int inverse, const cplx_real_t scale) {
    FFT_LOAD(4)
    dft4(&v[0], &v[1], &v[2], &v[3]);
    FFT_STORE(4)
}

__kernel void azimuth_fft_radix8(__global const cplx_t *restrict x, __global cplx_t *restrict y,
                                 __global const cplx_t *restrict twiddle, const int n, const int n_cols,
                                 const int ns, const int inverse, const cplx_real_t scale) {
    FFT_LOAD(8)
    /* even and odd halves, then combine with exp(-2 pi i k / 8) */
    dft4(&v[0], &v[2], &v[4], &v[6]);
    dft4(&v[1], &v[3], &v[5], &v[7]);
    const cplx_real_t h = (cplx_real_t)0.70710678118654752440;
    const cplx_t o1 = (cplx_t)(h * (v[3].x + v[3].y), h * (v[3].y - v[3].x));    /* W8^1 O[1] */
    const cplx_t o2 = mul_minus_i(v[5]);                                          /* W8^2 O[2] */
    const cplx_t o3 = (cplx_t)(h * (v[7].y - v[7].x), -h * (v[7].x + v[7].y));   /* W8^3 O[3] */
    const cplx_t e0 = v[0], e1 = v[2], e2 = v[4], e3 = v[6], o0 = v[1];
    v[0] = e0 + o0;
    v[4] = e0 - o0;
    v[1] = e1 + o1;
    v[5] = e1 - o1;
    v[2] = e2 + o2;
    v[6] = e2 - o2;
    v[3] = e3 + o3;
    v[7] = e3 - o3;
    FFT_STORE(8)
}
