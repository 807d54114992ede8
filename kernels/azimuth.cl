/* Azimuth stages of the modified NLCS chain (paper eqs. 12-17). Every phase function is evaluated from a
 * few scalars per range bin; work item (j, row): range bin j, azimuth sample (time or frequency) row. */

/* H5 (eq. 13) and H6, the NLCS filter (eq. 15): exp(-j pi eta1 f_a) exp(j pi (Y3 f_a^3 + Y4 f_a^4)).
 * Work item (q, row): range bins 4q..4q+3 (common.cl, c4). Row `row` holds FFT-order azimuth frequency
 * (row + row_origin) mod n_azimuth: row_origin 0 for a whole spectrum, the first row's index for a band of rows
 * (common.cl, azimuth_index). */
__kernel void nlcs_filter(__global float2 *restrict s, __global const real_t *restrict eta1,
                          __global const real_t *restrict y3, __global const real_t *restrict y4, const int n_range,
                          const int n_azimuth, const real_t azimuth_df_hz, const int row_origin) {
    const int j = 4 * get_global_id(0), row = get_global_id(1);
    if (j >= n_range) return;
    __global float2 *line = s + row * n_range;
    const c4 v = c4_load_lanes(line, j, n_range);
    if (all(v.re == 0.0f) && all(v.im == 0.0f)) return;  /* outside the Doppler band (most of a padded spectrum) */
    const real_t f = azimuth_index(row, row_origin, n_azimuth) * azimuth_df_hz;
    const real4_t phase = UWBCL_PI * f * (f * f * (real4_load(y3, j, n_range) + real4_load(y4, j, n_range) * f)
                                          - real4_load(eta1, j, n_range));
    c4_store_lanes(line, j, n_range, c4_mul(v, cis4(phase)));
}

/* H7, the nonlinear chirp scaling function (eq. 15): exp(j pi (q2 t^2 + q3 t^3 + q4 t^4)), absolute t_a.
 * Work item (q, row): range bins 4q..4q+3. */
__kernel void nlcs_scaling(__global float2 *restrict s, __global const real_t *restrict q2,
                           __global const real_t *restrict q3, __global const real_t *restrict q4,
                           const int n_range, const int n_azimuth, const real_t azimuth_dt_s) {
    const int j = 4 * get_global_id(0), row = get_global_id(1);
    if (j >= n_range) return;
    __global float2 *line = s + row * n_range;
    const real_t t = signed_index(row, n_azimuth) * azimuth_dt_s;
    const real4_t phase = UWBCL_PI * t * t * (real4_load(q2, j, n_range)
                                              + t * (real4_load(q3, j, n_range) + t * real4_load(q4, j, n_range)));
    c4_store_lanes(line, j, n_range, c4_mul(c4_load_lanes(line, j, n_range), cis4(phase)));
}

/* H8, azimuth compression (eq. 17; C10, C11): exp(-j sum_d a_d (f_a / f_scale)^d) inside the bin's band, zero
 * outside; `poly` holds degree + 1 ascending coefficients per bin. The band is given as signed frequency
 * indices [band_first, band_last] (decided on the host, so band edges that fall on a grid frequency are
 * treated exactly as the reference treats them). Work item (q, row): range bins 4q..4q+3 (common.cl, c4). */
__kernel void azimuth_compression(__global cplx_t *restrict s, __global const real_t *restrict poly, const int n_coeff,
                                  __global const int *restrict band_first, __global const int *restrict band_last,
                                  const int n_range, const int n_azimuth, const real_t azimuth_df_hz,
                                  const real_t f_scale_hz, const int row_origin) {
    const int j = 4 * get_global_id(0), row = get_global_id(1);
    if (j >= n_range) return;
    const int i = azimuth_index(row, row_origin, n_azimuth);
    const real_t u = i * azimuth_df_hz / f_scale_hz;
    const int4 bin = min(j + (int4)(0, 1, 2, 3), n_range - 1);  /* lanes past n_range repeat the last bin */
    const int4 in = (i >= (int4)(band_first[bin.s0], band_first[bin.s1], band_first[bin.s2], band_first[bin.s3]))
                    & (i <= (int4)(band_last[bin.s0], band_last[bin.s1], band_last[bin.s2], band_last[bin.s3]));
    __global cplx_t *line = s + row * n_range;
    c4 v = {(float4)0.0f, (float4)0.0f};
    if (any(in)) {
        const int4 at = bin * n_coeff;
        real4_t phase = 0;
        for (int d = n_coeff - 1; d >= 0; --d)  /* Horner */
            phase = phase * u + (real4_t)(poly[at.s0 + d], poly[at.s1 + d], poly[at.s2 + d], poly[at.s3 + d]);
        const c4 h = c4_mul(c4_load_lanes(line, j, n_range), cis4(-phase));
        v.re = select(v.re, h.re, in);
        v.im = select(v.im, h.im, in);
    }
    c4_store_lanes(line, j, n_range, v);
}

/* The slow-time signal, in range bin r, of a point target at azimuth time t_n after LRWC, SRC and RC (C11):
 * w(t) exp{-j 4 pi / lambda [R(t) + v s_q t]} with r0 = r - v s_q t_n, one target per column: the
 * exact-reference H8 is matched to the t_n = 0 target of each bin seen through the whole beam
 * (half_track_s < 0), detection's t_n(t_f) calibration simulates targets seen from the rail only
 * (|t| <= half_track_s). Two-way main-lobe beam sinc^2(D sin(psi - theta) / lambda) about the slant squint
 * theta. Work item (q, row): columns 4q..4q+3. */
__kernel void point_response(__global float2 *restrict out, __global const real_t *restrict r_m,
                             __global const real_t *restrict t_n_s, const int n_cols, const int n_azimuth,
                             const real_t azimuth_dt_s, const real_t speed_m_s, const real_t sin_squint,
                             const real_t wavelength_m, const real_t aperture_m, const real_t half_track_s) {
    const int j = 4 * get_global_id(0), row = get_global_id(1);
    if (j >= n_cols) return;
    const real_t t = signed_index(row, n_azimuth) * azimuth_dt_s;
    c4 v = {0.0f, 0.0f};
    if (half_track_s >= 0 && fabs(t) > half_track_s + 1e-12) {  /* off the rail */
        c4_store_lanes(out + row * n_cols, j, n_cols, v);
        return;
    }
    const real4_t t_n = real4_load(t_n_s, j, n_cols);
    const real4_t r0 = real4_load(r_m, j, n_cols) - speed_m_s * sin_squint * t_n;
    const real4_t vtau = speed_m_s * (t - t_n);
    const real4_t rng = sqrt(r0 * r0 + vtau * vtau - 2.0 * sin_squint * r0 * vtau);
    const real4_t sin_look = (r0 * sin_squint - vtau) / rng;
    const real4_t cos_look = sqrt(fmax(1.0 - sin_look * sin_look, 0.0));
    const real_t cos_squint = sqrt(1.0 - sin_squint * sin_squint);
    const float4 u = convert_float4(aperture_m * (sin_look * cos_squint - cos_look * sin_squint) / wavelength_m);
    const int4 in_lobe = fabs(u) < 1.0f;
    if (any(in_lobe)) {  /* outside the main lobe (most of the padded slow time) no phase is needed */
        const float4 x = (float)UWBCL_PI * u;
        const float4 sinc = select(sincos4(x).im / x, (float4)1.0f, x == 0.0f);
        const float4 beam = select((float4)0.0f, sinc * sinc, in_lobe);
        const c4 phasor = cis4(-2.0 * UWBCL_TWO_PI / wavelength_m * (rng + speed_m_s * sin_squint * t));
        v.re = beam * phasor.re;
        v.im = beam * phasor.im;
    }
    c4_store_lanes(out + row * n_cols, j, n_cols, v);
}
