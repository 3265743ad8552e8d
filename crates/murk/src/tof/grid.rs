//! A stream's start on a grid coarser than its frames.
//!
//! Fog's backscatter varies slowly across the image: the true scatter averaged over 2×2 blocks
//! and interpolated back costs at most 0.1 mm of range over the sensor-noise floor on every
//! simulated 512×424 frame, and the x-step's work follows the pixels (docs/benchmarks.md, "The
//! scatter on a coarser grid"). [`IrlsStart::box_downsampled`] carries a stream's start to the
//! grid of a frame's block means ([`block_means`]), for a caller that solves the frames after
//! the first on that grid (`tof_stream_survey --cold-full-size` does).

use super::irls::IrlsStart;
use crate::error::{MurkError, Result};

impl IrlsStart {
    /// This start (of `width × height` frames) on the grid of `factor × factor` block means:
    /// each scatter component and the weights averaged over the blocks, and σ₁ divided by
    /// `factor`, as the noise of a mean of `factor²` pixels is. Errors name `factor` when it is
    /// 0 or does not divide both sides, and `start` when the images are not `width × height`.
    pub fn box_downsampled(&self, width: usize, height: usize, factor: usize) -> Result<Self> {
        let n = width * height;
        if self.weights.len() != n || self.scatter.iter().any(|c| c.len() != n) {
            return Err(MurkError::invalid(
                "start",
                format!("its images are not the frame's {width}×{height}"),
            ));
        }
        let means = |values: &[f64]| block_means(values, width, height, factor);
        Ok(Self {
            scatter: self
                .scatter
                .iter()
                .map(|c| means(c))
                .collect::<Result<_>>()?,
            weights: means(&self.weights)?,
            sigma_fine: self.sigma_fine.map(|s| s / factor as f64),
        })
    }
}

/// `values` (`width × height`, row-major) averaged over `factor × factor` blocks, row-major on
/// the coarse grid. Errors name `factor` when it is 0 or does not divide both sides, and
/// `values` when there are not `width × height` of them.
pub fn block_means(values: &[f64], width: usize, height: usize, factor: usize) -> Result<Vec<f64>> {
    if factor == 0 || !width.is_multiple_of(factor) || !height.is_multiple_of(factor) {
        return Err(MurkError::invalid(
            "factor",
            format!("{factor} must be at least 1 and divide the frame's {width}×{height}"),
        ));
    }
    if values.len() != width * height {
        return Err(MurkError::invalid(
            "values",
            format!("{} values for a {width}×{height} grid", values.len()),
        ));
    }
    let cw = width / factor;
    let mut out = vec![0.0; cw * (height / factor)];
    for (y, row) in values.chunks_exact(width).enumerate() {
        let coarse = &mut out[(y / factor) * cw..(y / factor + 1) * cw];
        for (x, &v) in row.iter().enumerate() {
            coarse[x / factor] += v;
        }
    }
    let inv = 1.0 / (factor * factor) as f64;
    out.iter_mut().for_each(|v| *v *= inv);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn start(width: usize, height: usize) -> IrlsStart {
        let ramp = |k: f64| {
            (0..width * height)
                .map(|i| k * i as f64)
                .collect::<Vec<_>>()
        };
        IrlsStart {
            scatter: vec![ramp(1.0), ramp(-2.0)],
            weights: (0..width * height).map(|i| (i % 2) as f64).collect(),
            sigma_fine: Some(3.0),
        }
    }

    #[test]
    fn blocks_average_their_pixels_and_the_noise_scale_shrinks() {
        let s = start(4, 2).box_downsampled(4, 2, 2).unwrap();
        // Blocks {0, 1, 4, 5} and {2, 3, 6, 7}.
        assert_eq!(s.scatter[0], vec![2.5, 4.5]);
        assert_eq!(s.scatter[1], vec![-5.0, -9.0]);
        assert_eq!(s.weights, vec![0.5, 0.5]);
        assert_eq!(s.sigma_fine, Some(1.5));
    }

    #[test]
    fn factor_one_keeps_the_start() {
        let s = start(6, 3);
        assert_eq!(s.box_downsampled(6, 3, 1).unwrap(), s);
    }

    #[test]
    fn bad_factors_and_sizes_are_refused_naming_the_field() {
        let s = start(6, 4);
        for factor in [0, 4, 5] {
            let e = s.box_downsampled(6, 4, factor).unwrap_err().to_string();
            assert!(e.contains("factor"), "{e}");
        }
        let e = s.box_downsampled(8, 4, 2).unwrap_err().to_string();
        assert!(e.contains("start"), "{e}");
        let e = block_means(&[1.0; 5], 2, 2, 1).unwrap_err().to_string();
        assert!(e.contains("values"), "{e}");
    }
}
