/* Time-domain backprojection onto the slant plane (the exact reference focuser, paper section 4.2). */

/* Matched filter H4 (eq. 10) and zero-padding of each pulse's range spectrum for band-limited upsampling by
 * n_fine / n_range (the scale makes the normalised inverse FFT return the upsampled signal itself).
 * Work item (c, p): fine spectrum bin c of pulse p. */
__kernel void pulse_compression_upsample(__global const float2 *spec, __global float2 *fine, const int n_range,
                                         const int n_fine, const real_t sample_rate_hz,
                                         const real_t pulse_sigma_s) {
    const int c = get_global_id(0), p = get_global_id(1);
    if (c >= n_fine) return;
    const int n_low = n_range / 2;
    int src = -1;
    if (c < n_low) src = c;
    else if (c >= n_fine - (n_range - n_low)) src = c - n_fine + n_range;
    float2 v = (float2)(0.0f, 0.0f);
    if (src >= 0) {
        const real_t a = UWBCL_PI * pulse_sigma_s * (signed_index(src, n_range) * sample_rate_hz / n_range);
        v = (float)(exp(-2.0 * a * a) * n_fine / n_range) * spec[p * n_range + src];
    }
    fine[p * n_fine + c] = v;
}

/* The sum over the pulses whose slant squint lies in the beam's Doppler band [lo, hi] of the linearly
 * interpolated range-compressed echo at the exact two-way delay, for four points at once (lanes): x_m along the
 * rail (relative to the aperture centre) and closest-approach range rc_m, with the carrier phase k (R - R_c)
 * restored; the caller applies k R_c. The loop runs in float: k (R - R_c) = k dx^2 / (R + R_c) has no
 * cancellation, which keeps the phase error near 1e-5 rad. Explicit float4, as the four-bin kernels of
 * common.cl: PoCL runs a per-work-item loop with branches and gathers as scalar code, and its native sine and
 * cosine as scalar calls (measured on a 299 x 50 rib lattice, 243 pulses: 49 ms with one point per work item).
 * A pulse none of the four lanes sees is skipped; the others are masked per lane. *summed gets the number of
 * pulses each lane summed. */
inline c4 sum_over_pulses4(__global const float2 *restrict rc, __global const float *restrict x_rel_m,
                           const int n_pulses, const int n_fine, const float4 x_m, const float4 rc_m,
                           const float k, const float lo, const float hi, const float samples_per_m,
                           const float first, int4 *summed) {
    const float4 rc2 = rc_m * rc_m;
    c4 acc = {(float4)0.0f, (float4)0.0f};
    int4 n = (int4)0;
    for (int p = 0; p < n_pulses; ++p) {
        const float4 dx = x_m - x_rel_m[p];
        const float4 rng = sqrt(dx * dx + rc2);
        const float4 pos = rng * samples_per_m - first;
        const float4 fl = floor(pos);
        const int4 in = (dx >= lo * rng) & (dx <= hi * rng) & (fl >= 0.0f) & (fl < (float)(n_fine - 1));
        if (!any(in)) continue;
        const int4 i = select((int4)0, convert_int4(fl), in) + p * n_fine;
        const float4 frac = pos - fl;
        const float2 a0 = rc[i.s0], a1 = rc[i.s1], a2 = rc[i.s2], a3 = rc[i.s3];
        const float2 b0 = rc[i.s0 + 1], b1 = rc[i.s1 + 1], b2 = rc[i.s2 + 1], b3 = rc[i.s3 + 1];
        const c4 sample = {mix((float4)(a0.x, a1.x, a2.x, a3.x), (float4)(b0.x, b1.x, b2.x, b3.x), frac),
                           mix((float4)(a0.y, a1.y, a2.y, a3.y), (float4)(b0.y, b1.y, b2.y, b3.y), frac)};
        const float4 phase = k * dx * dx / (rng + rc_m);
        const c4 v = c4_mul(sample, sincos4(phase - (float)UWBCL_TWO_PI * rint(phase * (float)UWBCL_INV_TWO_PI)));
        acc.re += select((float4)0.0f, v.re, in);
        acc.im += select((float4)0.0f, v.im, in);
        n -= in;  /* a true lane of a vector comparison is -1 */
    }
    *summed = n;
    return acc;
}

/* Four pixels per work item (range pixels 4 i_r .. 4 i_r + 3 of row i_u) on the (u = v t_n, r_LRCM) axes:
 * `sum_over_pulses4` at their track coordinates, times exp(i k R_c) in real_t. P1: r0 = r - s_q u,
 * x_M = u + r0 s_q, R_c = r0 c_q. */
__kernel void backproject(__global const float2 *restrict rc, __global const float *restrict x_rel_m,
                          __global float2 *restrict image, const int n_pulses, const int n_fine,
                          const real_t t0_s, const real_t fine_dt_s, const int n_u, const int n_r,
                          const real_t u0_m, const real_t du_m, const real_t r_start_m, const real_t dr_m,
                          const real_t sin_squint, const real_t carrier_hz, const real_t band_lo,
                          const real_t band_hi) {
    const int j = 4 * get_global_id(0), iu = get_global_id(1);
    if (j >= n_r || iu >= n_u) return;
    const real_t u = u0_m + iu * du_m;
    const real4_t r = r_start_m + convert_real4((int4)(j, j + 1, j + 2, j + 3)) * dr_m;
    const real4_t r0 = r - sin_squint * u;
    const real_t k = 2.0 * UWBCL_TWO_PI * carrier_hz / UWBCL_C;
    const real4_t rc_pixel = r0 * sqrt(1.0 - sin_squint * sin_squint);
    int4 summed;
    const c4 acc = sum_over_pulses4(rc, x_rel_m, n_pulses, n_fine, convert_float4(u + r0 * sin_squint),
                                    convert_float4(rc_pixel), (float)k, (float)band_lo, (float)band_hi,
                                    (float)(2.0 / (UWBCL_C * fine_dt_s)), (float)(t0_s / fine_dt_s), &summed);
    c4_store_lanes(image + iu * n_r, j, n_r, c4_mul(acc, cis4(k * rc_pixel)));
}

/* The BP value at arbitrary points of the rig frame, four points per work item: x_m along the rail relative to
 * the aperture centre, rc_m the closest-approach range; the same sum as `backproject` (the numpy oracle is
 * backprojection.backproject_track_points: the rib registration's lattices, eq. R1, and the carrier phases,
 * eq. R5). counts[j] is the number of pulses summed. Split phase as in `backproject`. */
__kernel void backproject_track_points(__global const float2 *restrict rc, __global const float *restrict x_rel_m,
                                       __global const real_t *restrict x_m, __global const real_t *restrict rc_m,
                                       __global float2 *restrict out, __global int *restrict counts,
                                       const int n_points, const int n_pulses, const int n_fine,
                                       const real_t t0_s, const real_t fine_dt_s, const real_t carrier_hz,
                                       const real_t band_lo, const real_t band_hi) {
    const int j = 4 * get_global_id(0);
    if (j >= n_points) return;
    const real_t k = 2.0 * UWBCL_TWO_PI * carrier_hz / UWBCL_C;
    const real4_t x = real4_load(x_m, j, n_points), r = real4_load(rc_m, j, n_points);
    int4 summed;
    const c4 acc = sum_over_pulses4(rc, x_rel_m, n_pulses, n_fine, convert_float4(x), convert_float4(r),
                                    (float)k, (float)band_lo, (float)band_hi,
                                    (float)(2.0 / (UWBCL_C * fine_dt_s)), (float)(t0_s / fine_dt_s), &summed);
    c4_store_lanes(out, j, n_points, c4_mul(acc, cis4(k * r)));
    int n[4];
    vstore4(summed, 0, n);
    for (int l = 0; l < 4 && j + l < n_points; ++l)
        counts[j + l] = n[l];
}
