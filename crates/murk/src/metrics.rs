//! Accuracy metrics for depth maps and masks, following the reference's §3.4.3 (after Wang & Shen
//! and Eigen et al.): L1-rel, L1-inv, sc-inv and C.P., plus the plain mean absolute error.
//!
//! Pixel selection, shared by every depth metric: a pixel is *evaluated* when its ground truth is
//! finite and > 0 and the optional mask is > 0.5 there. Of those, a pixel whose prediction is
//! non-finite or ≤ 0 is a *missing prediction*: it is excluded from MAE, L1-rel, L1-inv and sc-inv
//! (they are undefined there) but counts as incorrect in C.P., and [`DepthMetrics`] reports how
//! many there were, so a method cannot improve its score by abstaining unnoticed.
//! Depth units are the caller's (metres throughout murk); MAE is in those units, L1-inv in their
//! inverse, the rest are unitless.

use serde::{Deserialize, Serialize};

use crate::error::{MurkError, Result};
use crate::image::ImageF32;

/// Relative-error threshold of C.P. ("correctly estimated depth percentage", §3.4.3).
pub const C_P_THRESHOLD: f64 = 0.1;

/// All depth metrics of one prediction.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthMetrics {
    /// Mean absolute error `mean |p − g|`, depth units.
    pub mae: f64,
    /// Mean relative error `mean |p − g| / g`.
    pub l1_rel: f64,
    /// Mean inverse-depth error `mean |1/p − 1/g|`, inverse depth units.
    pub l1_inv: f64,
    /// Scale-invariant log error `sqrt(mean(d²) − mean(d)²)`, `d = ln p − ln g` (Eigen et al.
    /// 2014 with λ = 1, square-rooted as in the MVDepthNet/DeMoN evaluations the reference uses).
    pub sc_inv: f64,
    /// Share of evaluated pixels with `|p − g|/g < 0.1`, as a fraction in [0, 1] (the reference's
    /// tables print it ×100 as "C.P. (%)"). Missing predictions count as incorrect.
    pub c_p: f64,
    /// Evaluated pixels (valid ground truth inside the mask).
    pub evaluated_pixels: usize,
    /// Evaluated pixels whose prediction was non-finite or ≤ 0.
    pub missing_predictions: usize,
}

/// Checks that `img` is one-channel and the same size as `gt`; errors name `field`.
fn check_like(img: &ImageF32, gt: &ImageF32, field: &str) -> Result<()> {
    img.ensure_channels(1).map_err(|e| e.within(field))?;
    if img.dims() != gt.dims() {
        return Err(MurkError::invalid(
            field,
            format!(
                "size {}x{} differs from gt {}x{}",
                img.width(),
                img.height(),
                gt.width(),
                gt.height()
            ),
        ));
    }
    Ok(())
}

/// A mask sample marks a valid pixel when > 0.5 (NaN: invalid).
fn mask_set(v: f32) -> bool {
    v > 0.5
}

/// Visits `(pred, gt)` of every evaluated pixel (see module docs); returns (evaluated, missing).
fn for_each_pair(
    pred: &ImageF32,
    gt: &ImageF32,
    mask: Option<&ImageF32>,
    mut f: impl FnMut(f64, f64),
) -> Result<(usize, usize)> {
    gt.ensure_channels(1).map_err(|e| e.within("gt"))?;
    check_like(pred, gt, "pred")?;
    if let Some(m) = mask {
        check_like(m, gt, "mask")?;
    }
    let (mut evaluated, mut missing) = (0usize, 0usize);
    for i in 0..gt.pixel_count() {
        let g = f64::from(gt.data()[i]);
        if !g.is_finite() || g <= 0.0 || mask.is_some_and(|m| !mask_set(m.data()[i])) {
            continue;
        }
        evaluated += 1;
        let p = f64::from(pred.data()[i]);
        if !p.is_finite() || p <= 0.0 {
            missing += 1;
            continue;
        }
        f(p, g);
    }
    Ok((evaluated, missing))
}

fn mean_of(
    pred: &ImageF32,
    gt: &ImageF32,
    mask: Option<&ImageF32>,
    err: impl Fn(f64, f64) -> f64,
) -> Result<f64> {
    let (mut sum, mut n) = (0.0, 0usize);
    for_each_pair(pred, gt, mask, |p, g| {
        sum += err(p, g);
        n += 1;
    })?;
    if n == 0 {
        return Err(MurkError::invalid(
            "gt",
            "no pixel has both a valid ground truth and a valid prediction",
        ));
    }
    Ok(sum / n as f64)
}

/// Mean absolute error `mean |p − g|` over evaluated pixels with a prediction.
pub fn mean_abs_error(pred: &ImageF32, gt: &ImageF32, mask: Option<&ImageF32>) -> Result<f64> {
    mean_of(pred, gt, mask, |p, g| (p - g).abs())
}

/// L1-rel: `mean |p − g| / g`.
pub fn l1_rel(pred: &ImageF32, gt: &ImageF32, mask: Option<&ImageF32>) -> Result<f64> {
    mean_of(pred, gt, mask, |p, g| (p - g).abs() / g)
}

/// L1-inv: `mean |1/p − 1/g|`.
pub fn l1_inv(pred: &ImageF32, gt: &ImageF32, mask: Option<&ImageF32>) -> Result<f64> {
    mean_of(pred, gt, mask, |p, g| (1.0 / p - 1.0 / g).abs())
}

/// sc-inv: `sqrt(mean(d²) − mean(d)²)` with `d = ln p − ln g`; 0 when `p = k·g` for any `k > 0`.
pub fn sc_inv(pred: &ImageF32, gt: &ImageF32, mask: Option<&ImageF32>) -> Result<f64> {
    let (mut s1, mut s2, mut n) = (0.0, 0.0, 0usize);
    for_each_pair(pred, gt, mask, |p, g| {
        let d = p.ln() - g.ln();
        s1 += d;
        s2 += d * d;
        n += 1;
    })?;
    if n == 0 {
        return Err(MurkError::invalid(
            "gt",
            "no pixel has both a valid ground truth and a valid prediction",
        ));
    }
    let m = s1 / n as f64;
    // Rounding can push the variance a hair below zero for a perfectly scaled prediction.
    Ok((s2 / n as f64 - m * m).max(0.0).sqrt())
}

/// C.P.: fraction (not percent) of evaluated pixels with relative error below 10 %; missing
/// predictions count as incorrect.
pub fn completeness_c_p(pred: &ImageF32, gt: &ImageF32, mask: Option<&ImageF32>) -> Result<f64> {
    let mut good = 0usize;
    let (evaluated, _) = for_each_pair(pred, gt, mask, |p, g| {
        if (p - g).abs() / g < C_P_THRESHOLD {
            good += 1;
        }
    })?;
    if evaluated == 0 {
        return Err(MurkError::invalid(
            "gt",
            "no pixel has a valid ground truth",
        ));
    }
    Ok(good as f64 / evaluated as f64)
}

/// All depth metrics in one pass over the images.
pub fn depth_metrics(
    pred: &ImageF32,
    gt: &ImageF32,
    mask: Option<&ImageF32>,
) -> Result<DepthMetrics> {
    let (mut abs, mut rel, mut inv, mut s1, mut s2) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let (mut n, mut good) = (0usize, 0usize);
    let (evaluated, missing) = for_each_pair(pred, gt, mask, |p, g| {
        let e = (p - g).abs();
        abs += e;
        rel += e / g;
        inv += (1.0 / p - 1.0 / g).abs();
        let d = p.ln() - g.ln();
        s1 += d;
        s2 += d * d;
        n += 1;
        if e / g < C_P_THRESHOLD {
            good += 1;
        }
    })?;
    if n == 0 {
        return Err(MurkError::invalid(
            "gt",
            "no pixel has both a valid ground truth and a valid prediction",
        ));
    }
    let nf = n as f64;
    let m = s1 / nf;
    Ok(DepthMetrics {
        mae: abs / nf,
        l1_rel: rel / nf,
        l1_inv: inv / nf,
        sc_inv: (s2 / nf - m * m).max(0.0).sqrt(),
        c_p: good as f64 / evaluated as f64,
        evaluated_pixels: evaluated,
        missing_predictions: missing,
    })
}

/// Intersection over union of two masks (> 0.5 = set; non-finite = unset). Two empty masks agree
/// perfectly (IoU 1).
pub fn mask_iou(pred: &ImageF32, gt: &ImageF32) -> Result<f64> {
    gt.ensure_channels(1).map_err(|e| e.within("gt"))?;
    check_like(pred, gt, "pred")?;
    let (mut inter, mut union) = (0usize, 0usize);
    for (&p, &g) in pred.data().iter().zip(gt.data()) {
        let (p, g) = (p > 0.5, g > 0.5);
        inter += usize::from(p && g);
        union += usize::from(p || g);
    }
    Ok(if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    })
}

/// Mean angular error between unit normals, degrees, over `mask` (the reference's normal metric,
/// Table 4.1). Normals need not be normalised; pixels where either is zero or non-finite are
/// skipped. Fails when the lengths differ or nothing is evaluated.
pub fn mean_angular_error_deg(pred: &[[f32; 3]], gt: &[[f32; 3]], mask: &[bool]) -> Result<f64> {
    if pred.len() != gt.len() || mask.len() != gt.len() {
        return Err(MurkError::invalid(
            "pred",
            format!(
                "{} predicted, {} ground-truth normals and {} mask entries",
                pred.len(),
                gt.len(),
                mask.len()
            ),
        ));
    }
    let (mut sum, mut count) = (0.0f64, 0usize);
    for ((a, b), &m) in pred.iter().zip(gt).zip(mask) {
        if !m {
            continue;
        }
        let a = a.map(f64::from);
        let b = b.map(f64::from);
        let na = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        let nb = (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]).sqrt();
        if !(na > 0.0 && nb > 0.0 && na.is_finite() && nb.is_finite()) {
            continue;
        }
        let c = ((a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) / (na * nb)).clamp(-1.0, 1.0);
        sum += c.acos().to_degrees();
        count += 1;
    }
    if count == 0 {
        return Err(MurkError::invalid("mask", "no pixel to evaluate"));
    }
    Ok(sum / count as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(v: &[f32]) -> ImageF32 {
        ImageF32::from_vec(v.len(), 1, 1, v.to_vec()).unwrap()
    }

    fn close(a: f64, b: f64) {
        // Inputs are f32: agree to f32 precision.
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }

    #[test]
    fn hand_computed_values() {
        // gt 1, 2, 4, 2; pred 1.05, 1.5, 4, 2.4.
        let gt = img(&[1.0, 2.0, 4.0, 2.0]);
        let pred = img(&[1.05, 1.5, 4.0, 2.4]);
        // |e| = .05, .5, 0, .4 → MAE = .95/4.
        close(mean_abs_error(&pred, &gt, None).unwrap(), 0.2375);
        // rel = .05, .25, 0, .2 → .5/4.
        close(l1_rel(&pred, &gt, None).unwrap(), 0.125);
        // inv: |1/1.05 − 1| + |1/1.5 − .5| + 0 + |1/2.4 − .5|.
        let inv =
            (1.0 / 1.05f32 as f64 - 1.0).abs() + (1.0 / 1.5 - 0.5) + (0.5 - 1.0 / 2.4f32 as f64);
        close(l1_inv(&pred, &gt, None).unwrap(), inv / 4.0);
        // C.P.: rel < .1 for pixels 0 and 2 → 0.5.
        close(completeness_c_p(&pred, &gt, None).unwrap(), 0.5);
        let d: Vec<f64> = [(1.05f32, 1.0f32), (1.5, 2.0), (4.0, 4.0), (2.4, 2.0)]
            .iter()
            .map(|&(p, g)| f64::from(p).ln() - f64::from(g).ln())
            .collect();
        let m = d.iter().sum::<f64>() / 4.0;
        let var = d.iter().map(|x| x * x).sum::<f64>() / 4.0 - m * m;
        close(sc_inv(&pred, &gt, None).unwrap(), var.sqrt());
        let all = depth_metrics(&pred, &gt, None).unwrap();
        close(all.mae, 0.2375);
        close(all.l1_rel, 0.125);
        close(all.c_p, 0.5);
        close(all.sc_inv, var.sqrt());
        assert_eq!((all.evaluated_pixels, all.missing_predictions), (4, 0));
    }

    #[test]
    fn sc_inv_is_scale_invariant() {
        let gt = img(&[1.0, 2.0, 3.0, 7.5]);
        let pred = img(&[2.0, 4.0, 6.0, 15.0]);
        assert!(sc_inv(&pred, &gt, None).unwrap() < 1e-7);
        assert!(l1_rel(&pred, &gt, None).unwrap() > 0.99);
    }

    #[test]
    fn mask_invalid_gt_and_missing_predictions() {
        let gt = img(&[1.0, f32::NAN, 0.0, 2.0, 2.0]);
        let pred = img(&[1.0, 1.0, 1.0, f32::INFINITY, 3.0]);
        let m = depth_metrics(&pred, &gt, None).unwrap();
        // Evaluated: pixels 0, 3, 4; pixel 3 is a missing prediction.
        assert_eq!((m.evaluated_pixels, m.missing_predictions), (3, 1));
        close(m.mae, 0.5); // (0 + 1) / 2
        close(m.c_p, 1.0 / 3.0); // only pixel 0 correct; the missing one counts as wrong
        let mask = img(&[0.0, 1.0, 1.0, 1.0, 1.0]);
        let m = depth_metrics(&pred, &gt, Some(&mask)).unwrap();
        assert_eq!((m.evaluated_pixels, m.missing_predictions), (2, 1));
        close(m.mae, 1.0);
        assert!(mean_abs_error(&pred, &gt, Some(&img(&[0.0; 5]))).is_err());
        match depth_metrics(&img(&[1.0]), &gt, None) {
            Err(MurkError::InvalidArgument { field, .. }) => assert_eq!(field, "pred"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn iou_of_masks() {
        let a = img(&[1.0, 1.0, 0.0, 0.0, 1.0]);
        let b = img(&[1.0, 0.0, 1.0, 0.0, 1.0]);
        close(mask_iou(&a, &b).unwrap(), 0.5); // ∩ = 2, ∪ = 4
        close(mask_iou(&img(&[0.0; 3]), &img(&[0.0; 3])).unwrap(), 1.0);
        close(mask_iou(&a, &a).unwrap(), 1.0);
        assert!(mask_iou(&a, &img(&[1.0])).is_err());
    }
    #[test]
    fn angular_error_of_known_rotations() {
        let gt = vec![[0.0f32, 0.0, -1.0]; 3];
        let a = 10f32.to_radians();
        let pred = vec![
            [a.sin(), 0.0, -a.cos()],
            [0.0, 2.0 * a.sin(), -2.0 * a.cos()], // length 2: direction counts only
            [1.0, 0.0, 0.0],                      // masked out
        ];
        let e = mean_angular_error_deg(&pred, &gt, &[true, true, false]).unwrap();
        assert!((e - 10.0).abs() < 1e-4, "{e}");
        assert!(mean_angular_error_deg(&pred, &gt, &[false; 3]).is_err());
        assert!(mean_angular_error_deg(&pred[..2], &gt, &[true; 3]).is_err());
    }
}
