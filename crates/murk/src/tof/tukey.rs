//! Tukey's biweight (Eq. 5.14–5.15) and the median-absolute-deviation scale used to normalise the
//! IRLS residuals (§5.3.4).

/// Consistency factor turning a median absolute deviation into a Gaussian standard deviation.
pub const MAD_TO_SIGMA: f64 = 1.482_602_218_505_602;

/// Tukey's biweight loss ρ(x) (Eq. 5.14) for tuning constant `c > 0`.
#[inline]
pub fn rho(x: f64, c: f64) -> f64 {
    let c2_6 = c * c / 6.0;
    if x.abs() <= c {
        let t = 1.0 - (x / c) * (x / c);
        c2_6 * (1.0 - t * t * t)
    } else {
        c2_6
    }
}

/// IRLS weight ρ′(r)/r of Tukey's biweight (Eq. 5.13, 5.15), in [0, 1]; zero beyond `c`.
#[inline]
pub fn weight(r: f64, c: f64) -> f64 {
    if r.abs() <= c {
        let t = 1.0 - (r / c) * (r / c);
        t * t
    } else {
        0.0
    }
}

/// Median of `values`, reordering them in place (O(n) selection, no allocation).
/// Returns `None` for an empty slice or if any value is NaN.
pub fn median_in_place(values: &mut [f64]) -> Option<f64> {
    let n = values.len();
    if n == 0 || values.iter().any(|v| v.is_nan()) {
        return None;
    }
    let mid = n / 2;
    let (lo, m, _) = values.select_nth_unstable_by(mid, f64::total_cmp);
    let upper = *m;
    if n % 2 == 1 {
        Some(upper)
    } else {
        // Even count: average the two middle order statistics; the lower one is the max of `lo`.
        let lower = lo.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        Some(0.5 * (lower + upper))
    }
}

/// Robust standard deviation 1.4826·median(|v − median(v)|) (§5.3.4), reordering `values` in
/// place and overwriting them with absolute deviations. `None` when empty or NaN-tainted.
pub fn mad_sigma_in_place(values: &mut [f64]) -> Option<f64> {
    let med = median_in_place(values)?;
    for v in values.iter_mut() {
        *v = (*v - med).abs();
    }
    median_in_place(values).map(|m| MAD_TO_SIGMA * m)
}

/// Lower bound for a robust scale so a noiseless (e.g. constant) image divides by a positive
/// number instead of producing NaN weights: a millionth of the data's magnitude, never below
/// 1e-12 (all residuals exactly zero then still give weight 1).
pub fn scale_floor(data_magnitude: f64) -> f64 {
    (1e-6 * data_magnitude.abs()).max(1e-12)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rho_and_weight_values() {
        let c = 4.0;
        assert_eq!(rho(0.0, c), 0.0);
        assert!((rho(c, c) - c * c / 6.0).abs() < 1e-12);
        assert!((rho(10.0, c) - c * c / 6.0).abs() < 1e-12);
        // ρ(2) for c=4: (16/6)·(1 − (1 − 1/4)³) = (8/3)·(37/64).
        assert!((rho(2.0, c) - (8.0 / 3.0) * (37.0 / 64.0)).abs() < 1e-12);
        assert_eq!(weight(0.0, c), 1.0);
        assert!((weight(2.0, c) - 0.5625).abs() < 1e-12);
        assert!((weight(-2.0, c) - 0.5625).abs() < 1e-12);
        assert_eq!(weight(4.0, c), 0.0);
        assert_eq!(weight(5.0, c), 0.0);
        // w = ρ′(r)/r: check against a central difference of ρ.
        for r in [0.3, 1.0, 2.5, 3.9] {
            let h = 1e-6;
            let d = (rho(r + h, c) - rho(r - h, c)) / (2.0 * h);
            assert!((d / r - weight(r, c)).abs() < 1e-6, "r {r}");
        }
    }

    #[test]
    fn median_and_mad() {
        let mut v = vec![3.0, 1.0, 2.0];
        assert_eq!(median_in_place(&mut v), Some(2.0));
        let mut v = vec![4.0, 1.0, 3.0, 2.0];
        assert_eq!(median_in_place(&mut v), Some(2.5));
        assert_eq!(median_in_place(&mut []), None);
        assert_eq!(median_in_place(&mut [1.0, f64::NAN]), None);
        // Deviations from median 3 are [2,1,0,1,7] → MAD 1.
        let mut v = vec![1.0, 2.0, 3.0, 4.0, 10.0];
        let s = mad_sigma_in_place(&mut v).unwrap();
        assert!((s - MAD_TO_SIGMA).abs() < 1e-12);
        let mut c = vec![5.0; 10];
        assert_eq!(mad_sigma_in_place(&mut c), Some(0.0));
        assert!(scale_floor(0.0) > 0.0);
    }
}
