/* Range stages of the modified NLCS chain (paper eqs. 3-11). Work item (k, p): range sample k of row p, unless
 * said otherwise. */

/* eq. (3)-(4): restore the absolute delay origin of the range window, then H1, the linear range walk
 * correction exp(-j 4 pi (f_c + f_r) sin(theta_q) x_p / c) with x_p the LOGGED rail position of pulse p.
 * Work item (q, p): range frequencies 4q..4q+3 of row p (common.cl, c4). */
__kernel void range_walk_correction(__global float2 *restrict s, __global const real_t *restrict x_rel_m,
                                    const int n_range, const real_t sample_rate_hz, const real_t window_start_s,
                                    const real_t carrier_hz, const real_t sin_squint) {
    const int k = 4 * get_global_id(0), p = get_global_id(1);
    if (k >= n_range) return;
    const int4 lane = k + (int4)(0, 1, 2, 3);
    const int4 index = select(lane, lane - n_range, lane >= (n_range + 1) / 2);  /* signed_index */
    const real4_t f = convert_real4(index) * (sample_rate_hz / n_range);
    const real4_t phase = -UWBCL_TWO_PI * window_start_s * f
                          - (2.0 * UWBCL_TWO_PI * sin_squint * x_rel_m[p] / UWBCL_C) * (carrier_hz + f);
    __global float2 *row = s + p * n_range;
    c4_store_lanes(row, k, n_range, c4_mul(c4_load_lanes(row, k, n_range), cis4(phase)));
}

/* Motion compensation and padding: Lagrange interpolation from the logged pulses onto the uniform track
 * (weights from the host, `order` taps starting at pulse first[j]), H2 of the extended NLCS (eq. 6,
 * exp(+j 4 pi (f_c + f_r) p2 t_a^2 / c)), written into the zero-padded azimuth grid in FFT order.
 * Work item (k, row) of the (n_azimuth, n_range) output. */
__kernel void resample_to_uniform_track(__global const float2 *restrict s, __global float2 *restrict out,
                                        __global const int *restrict first, __global const real_t *restrict weights,
                                        const int order, const int n_track, const int n_azimuth,
                                        const int n_range, const real_t sample_rate_hz,
                                        const real_t carrier_hz, const real_t track_dt_s,
                                        const real_t p2_m_s2) {
    const int k = get_global_id(0), row = get_global_id(1);
    if (k >= n_range) return;
    const int t_index = signed_index(row, n_azimuth);
    const int j = t_index + (n_track - 1) / 2;
    float2 acc = (float2)(0.0f, 0.0f);
    if (j >= 0 && j < n_track) {
        for (int m = 0; m < order; ++m)
            acc += (float)weights[j * order + m] * s[(first[j] + m) * n_range + k];
        if (p2_m_s2 != 0) {
            const real_t f = signed_index(k, n_range) * sample_rate_hz / n_range;
            const real_t t = t_index * track_dt_s;
            acc = cmul(acc, cis(2.0 * UWBCL_TWO_PI * (carrier_hz + f) * p2_m_s2 * t * t / UWBCL_C));
        }
    }
    out[row * n_range + k] = acc;
}

/* eqs. (9)-(11), C5 and C6: H3 (bulk SRC with the reference target's exact 2-D spectrum phase), the beam's
 * Doppler-band mask, H4 (matched filter of the Gaussian pulse) and the delay origin of the range IFFT,
 * in one pass over the 2-D spectrum. Work item (q, row): range frequencies 4q..4q+3 (common.cl, c4), azimuth
 * frequency row (+ row_origin, as in azimuth.cl). */
__kernel void secondary_range_compression(__global float2 *restrict s, const int n_range, const int n_azimuth,
                                          const real_t sample_rate_hz, const real_t window_start_s,
                                          const real_t carrier_hz, const real_t azimuth_df_hz,
                                          const real_t speed_m_s, const real_t sin_squint,
                                          const real_t reference_range_m, const real_t pulse_sigma_s,
                                          const real_t band_lo, const real_t band_hi, const int row_origin) {
    const int k = 4 * get_global_id(0), row = get_global_id(1);
    if (k >= n_range) return;
    const int4 lane = k + (int4)(0, 1, 2, 3);
    const int4 index = select(lane, lane - n_range, lane >= (n_range + 1) / 2);  /* signed_index */
    const real4_t f_r = convert_real4(index) * sample_rate_hz / n_range;
    const real_t f_a = azimuth_index(row, row_origin, n_azimuth) * azimuth_df_hz;
    const real_t cos_squint = sqrt(1.0 - sin_squint * sin_squint);
    const real4_t x = sin_squint + UWBCL_C * f_a / (2.0 * speed_m_s * (carrier_hz + f_r));
    const real_t x0 = sin_squint + UWBCL_C * f_a / (2.0 * speed_m_s * carrier_hz);
    const int4 in = convert_int4((x >= band_lo) & (x <= band_hi) & (fabs(x) < SQUINT_SINE_CAP));
    __global float2 *line = s + row * n_range;
    c4 v = {(float4)0.0f, (float4)0.0f};
    if (any(in)) {
        const real4_t g = cos_squint * sqrt(fmax(1.0 - x * x, 0.0)) + sin_squint * x;
        const real_t g0 = cos_squint * sqrt(fmax(1.0 - x0 * x0, 0.0)) + sin_squint * x0;
        const real_t k_ref = 2.0 * UWBCL_TWO_PI * reference_range_m / UWBCL_C;
        const real4_t phi = -k_ref * (carrier_hz + f_r) * g;  /* eq. (7) under P1 */
        const real_t phi0 = -k_ref * carrier_hz * g0;
        const real4_t phase = -(phi - phi0 + k_ref * f_r) + UWBCL_TWO_PI * f_r * window_start_s;
        const real4_t a = UWBCL_PI * pulse_sigma_s * f_r;
        const float4 h4 = convert_float4(exp(-2.0 * a * a));
        const c4 h = c4_mul(c4_load_lanes(line, k, n_range), cis4(phase));
        v.re = select(v.re, h4 * h.re, in);
        v.im = select(v.im, h4 * h.im, in);
    }
    c4_store_lanes(line, k, n_range, v);
}

/* The measured pulse's matched filter H4 = conj(P(f_r)) (eq. 10), sampled on the range frequencies by the host
 * (`FocusGrid.pulse_filter`): s[row, k] *= h4[k]. The Gaussian's H4 stays in the kernels above (pulse_sigma_s);
 * with a measured pulse they get pulse_sigma_s = 0 (H4 = 1) and this kernel follows. */
__kernel void range_gain(__global float2 *restrict s, __global const float2 *restrict h4, const int n_range) {
    const int k = get_global_id(0), row = get_global_id(1);
    if (k >= n_range) return;
    s[row * n_range + k] = cmul(s[row * n_range + k], h4[k]);
}

/* Gather a band of azimuth rows: out[r] = full[(r + row_origin) mod n_azimuth] * filter[r]. The engine keeps a
 * pass's grid-only filters (SRC, H5/H6, H8 on their bands of rows) as tables computed once by the kernels above
 * from their scalars, and applies them to every echo of the pass (the image and detection's models). */
__kernel void gather_rows(__global const float2 *restrict full, __global float2 *restrict out,
                          __global const float2 *restrict filter, const int row_origin, const int n_azimuth,
                          const int n_range) {
    const int k = get_global_id(0), r = get_global_id(1);
    if (k >= n_range) return;
    const int row = (r + row_origin) % n_azimuth;
    out[r * n_range + k] = cmul(full[row * n_range + k], filter[r * n_range + k]);
}

/* The inverse of gather_rows without a filter: band rows back into a whole spectrum, zero elsewhere. */
__kernel void scatter_rows(__global const float2 *restrict band, __global float2 *restrict full,
                           const int row_origin, const int n_rows, const int n_azimuth, const int n_range) {
    const int k = get_global_id(0), row = get_global_id(1);
    if (k >= n_range) return;
    const int r = (row - row_origin + n_azimuth) % n_azimuth;
    full[row * n_range + k] = r < n_rows ? band[r * n_range + k] : (float2)(0.0f, 0.0f);
}

/* s *= filter, elementwise (a table made by the kernels above). */
__kernel void apply_filter(__global float2 *restrict s, __global const float2 *restrict filter, const int n_range) {
    const int k = get_global_id(0), row = get_global_id(1);
    if (k >= n_range) return;
    s[row * n_range + k] = cmul(s[row * n_range + k], filter[row * n_range + k]);
}
