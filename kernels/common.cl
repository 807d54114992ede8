/* Helpers shared by every uwbcl kernel.
 *
 * Data are single-precision complex (float2), row-major (azimuth, range). Phase arguments are evaluated in
 * real_t (double where the device has fp64, float otherwise), reduced modulo 2 pi in that precision, and
 * only then handed to float trigonometry: arguments reach ~1e3 rad (4 pi R / lambda), where float32
 * arithmetic alone would leave 1e-4 rad errors.
 *
 * Azimuth axes are stored in FFT (natural) order: element k is signed index k (k < N/2) or k - N (k >= N/2),
 * for time and frequency alike. The host's centred arrays are fftshift of these.
 */
#ifdef UWBCL_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real_t;
#else
typedef float real_t;
#endif

typedef float2 cplx_t;

/* Build-time constants from the host (`-D`), so each has one home in Python:
 * SQUINT_SINE_CAP  the largest |sine of the slant squint| the band mask admits (uwbcl.focus.nlcs). */
#ifndef SQUINT_SINE_CAP
#error "build with -DSQUINT_SINE_CAP (uwbcl.focus.nlcs.SQUINT_SINE_CAP)"
#endif

#define UWBCL_PI 3.14159265358979323846
#define UWBCL_TWO_PI 6.28318530717958647692
#define UWBCL_C 299792458.0

inline cplx_t cmul(cplx_t a, cplx_t b) {
    return (cplx_t)(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

#define UWBCL_INV_TWO_PI 0.15915494309189533577

/* exp(i phase). The argument is reduced to [-pi, pi] first, where the native (fast) sine and cosine are
 * accurate to a few 1e-7 on the devices we know (PoCL, NVIDIA); the full-range sincos is several times
 * slower on PoCL, where it is not vectorised. */
inline cplx_t cis(real_t phase) {
    const float reduced = (float)(phase - (real_t)UWBCL_TWO_PI * rint(phase * (real_t)UWBCL_INV_TWO_PI));
    return (float2)(native_cos(reduced), native_sin(reduced));
}

/* ---- four range bins per work item: explicit float4 arithmetic, which every runtime vectorises (PoCL does not
 * vectorise the scalar kernels above across work items, and its native sine and cosine are scalar calls). */
#ifdef UWBCL_FP64
typedef double4 real4_t;
#define convert_real4 convert_double4
#else
typedef float4 real4_t;
#define convert_real4 convert_float4
#endif

/* Four neighbouring complex samples as split real and imaginary parts. */
typedef struct {
    float4 re, im;
} c4;

/* Lanes j..j+3 of a row of n complex samples; lanes past n read as zero. */
inline c4 c4_load_lanes(__global const float2 *row, const int j, const int n) {
    if (j + 4 <= n) {
        const float8 v = vload8(0, (__global const float *)(row + j));
        const c4 a = {v.even, v.odd};
        return a;
    }
    float re[4] = {0.0f, 0.0f, 0.0f, 0.0f}, im[4] = {0.0f, 0.0f, 0.0f, 0.0f};
    for (int l = 0; l < 4 && j + l < n; ++l) {
        re[l] = row[j + l].x;
        im[l] = row[j + l].y;
    }
    const c4 a = {vload4(0, re), vload4(0, im)};
    return a;
}

/* Store lanes j..j+3 (those before n) of a row. */
inline void c4_store_lanes(__global float2 *row, const int j, const int n, const c4 a) {
    if (j + 4 <= n) {
        vstore8((float8)(a.re.s0, a.im.s0, a.re.s1, a.im.s1, a.re.s2, a.im.s2, a.re.s3, a.im.s3), 0,
                (__global float *)(row + j));
        return;
    }
    float re[4], im[4];
    vstore4(a.re, 0, re);
    vstore4(a.im, 0, im);
    for (int l = 0; l < 4 && j + l < n; ++l)
        row[j + l] = (float2)(re[l], im[l]);
}

/* Per-bin coefficients j..j+3; zero past n. */
inline real4_t real4_load(__global const real_t *p, const int j, const int n) {
    if (j + 4 <= n)
        return vload4(0, p + j);
    real_t v[4] = {0, 0, 0, 0};
    for (int l = 0; l < 4 && j + l < n; ++l)
        v[l] = p[j + l];
    return vload4(0, v);
}

inline c4 c4_mul(const c4 a, const c4 b) {
    const c4 r = {a.re * b.re - a.im * b.im, a.re * b.im + a.im * b.re};
    return r;
}

/* cos and sin of x in [-pi, pi]: quadrant reduction and the single-precision minimax polynomials of Cephes on
 * [-pi/4, pi/4], branch-free (absolute error 1.6e-7 measured, as native_cos/native_sin). */
inline c4 sincos4(const float4 x) {
    const float4 q = rint(x * 0.63661977236758134f);
    float4 r = fma(-q, (float4)1.5707963705062866f, x);
    r = fma(-q, (float4)-4.3711388286737929e-08f, r);
    const float4 r2 = r * r;
    const float4 s = fma(r * r2, fma(r2, fma(r2, (float4)-1.9515295891e-4f, (float4)8.3321608736e-3f),
                                     (float4)-1.6666654611e-1f), r);
    const float4 c = fma(r2 * r2, fma(r2, fma(r2, (float4)2.443315711809948e-5f, (float4)-1.388731625493765e-3f),
                                      (float4)4.166664568298827e-2f), fma((float4)-0.5f, r2, (float4)1.0f));
    const int4 quadrant = convert_int4(q) & 3;
    const int4 swap = (quadrant & 1) != 0;
    const float4 cv = select(c, s, swap), sv = select(s, c, swap);
    const c4 out = {select(cv, -cv, (quadrant == 1) | (quadrant == 2)), select(sv, -sv, (quadrant & 2) != 0)};
    return out;
}

/* exp(i phase), four at a time, reduced modulo 2 pi in real_t first (as `cis`). */
inline c4 cis4(const real4_t phase) {
    return sincos4(convert_float4(phase - (real_t)UWBCL_TWO_PI * rint(phase * (real_t)UWBCL_INV_TWO_PI)));
}

/* exp(i phase) in float throughout, for arguments small enough (|phase| < ~1e3) that float rounding of the
 * argument itself is within the error budget. */
inline float2 cis_f(float phase) {
    const float reduced = phase - (float)UWBCL_TWO_PI * rint(phase * (float)UWBCL_INV_TWO_PI);
    return (float2)(native_cos(reduced), native_sin(reduced));
}

/* Signed index of FFT-order position k on an axis of length n (numpy's fftfreq * n). */
inline int signed_index(int k, int n) {
    return k < (n + 1) / 2 ? k : k - n;
}

/* Signed azimuth index of row `row` of an array whose row 0 is FFT-order position row_origin (0 for a whole
 * axis; the first row's position for a band of rows). */
inline int azimuth_index(int row, int row_origin, int n) {
    return signed_index((row + row_origin) % n, n);
}
