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
typedef float cplx_real_t;

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
