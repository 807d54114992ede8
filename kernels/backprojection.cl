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
 * interpolated range-compressed echo at the exact two-way delay, for the point x_m along the rail (relative to
 * the aperture centre) and closest-approach range rc_m, with the carrier phase k (R - R_c) restored; the caller
 * applies k R_c. The loop runs in float: k (R - R_c) = k dx^2 / (R + R_c) has no cancellation, which keeps the
 * phase error near 1e-5 rad. *summed gets the number of pulses summed. */
inline float2 sum_over_pulses(__global const float2 *restrict rc, __global const float *restrict x_rel_m,
                              const int n_pulses, const int n_fine, const float x_m, const float rc_m,
                              const float k, const float lo, const float hi, const float samples_per_m,
                              const float first, int *summed) {
    const float rc2 = rc_m * rc_m;
    float2 acc = (float2)(0.0f, 0.0f);
    int n = 0;
    for (int p = 0; p < n_pulses; ++p) {
        const float dx = x_m - x_rel_m[p];
        const float rng = sqrt(dx * dx + rc2);
        if (dx < lo * rng || dx > hi * rng) continue;
        const float pos = rng * samples_per_m - first;
        const float fl = floor(pos);
        if (fl < 0.0f || fl >= (float)(n_fine - 1)) continue;
        const int i = (int)fl;
        const float frac = pos - fl;
        const float2 sample = (1.0f - frac) * rc[p * n_fine + i] + frac * rc[p * n_fine + i + 1];
        acc += cmul(sample, cis_f(k * dx * dx / (rng + rc_m)));
        ++n;
    }
    *summed = n;
    return acc;
}

/* One pixel per work item (i_r, i_u) on the (u = v t_n, r_LRCM) axes: `sum_over_pulses` at its track
 * coordinates, times exp(i k R_c) in real_t. P1: r0 = r - s_q u, x_M = u + r0 s_q, R_c = r0 c_q. */
__kernel void backproject(__global const float2 *restrict rc, __global const float *restrict x_rel_m,
                          __global float2 *restrict image, const int n_pulses, const int n_fine,
                          const real_t t0_s, const real_t fine_dt_s, const int n_u, const int n_r,
                          const real_t u0_m, const real_t du_m, const real_t r_start_m, const real_t dr_m,
                          const real_t sin_squint, const real_t carrier_hz, const real_t band_lo,
                          const real_t band_hi) {
    const int ir = get_global_id(0), iu = get_global_id(1);
    if (ir >= n_r || iu >= n_u) return;
    const real_t u = u0_m + iu * du_m, r = r_start_m + ir * dr_m;
    const real_t r0 = r - sin_squint * u;
    const real_t k = 2.0 * UWBCL_TWO_PI * carrier_hz / UWBCL_C;
    const real_t rc_pixel = r0 * sqrt(1.0 - sin_squint * sin_squint);
    const float x_m = (float)(u + r0 * sin_squint), rc_m = (float)rc_pixel;
    int summed;
    const float2 acc = sum_over_pulses(rc, x_rel_m, n_pulses, n_fine, x_m, rc_m, (float)k, (float)band_lo,
                                       (float)band_hi, (float)(2.0 / (UWBCL_C * fine_dt_s)),
                                       (float)(t0_s / fine_dt_s), &summed);
    image[iu * n_r + ir] = cmul(acc, cis(k * rc_pixel));
}

/* The BP value at arbitrary points of the rig frame, one point per work item: x_m along the rail relative to
 * the aperture centre, rc_m the closest-approach range; the same sum as `backproject` (the numpy oracle is
 * backprojection.backproject_track_points: the rib registration's lattices, eq. R1, and the carrier phases,
 * eq. R5). counts[j] is the number of pulses summed. Split phase as in `backproject`. */
__kernel void backproject_track_points(__global const float2 *restrict rc, __global const float *restrict x_rel_m,
                                       __global const real_t *restrict x_m, __global const real_t *restrict rc_m,
                                       __global float2 *restrict out, __global int *restrict counts,
                                       const int n_points, const int n_pulses, const int n_fine,
                                       const real_t t0_s, const real_t fine_dt_s, const real_t carrier_hz,
                                       const real_t band_lo, const real_t band_hi) {
    const int j = get_global_id(0);
    if (j >= n_points) return;
    const real_t k = 2.0 * UWBCL_TWO_PI * carrier_hz / UWBCL_C;
    int summed;
    const float2 acc = sum_over_pulses(rc, x_rel_m, n_pulses, n_fine, (float)x_m[j], (float)rc_m[j], (float)k,
                                       (float)band_lo, (float)band_hi, (float)(2.0 / (UWBCL_C * fine_dt_s)),
                                       (float)(t0_s / fine_dt_s), &summed);
    out[j] = cmul(acc, cis(k * rc_m[j]));
    counts[j] = summed;
}
