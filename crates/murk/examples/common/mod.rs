//! Flags and output shared by the survey examples (`mod common;` in each). Each survey uses a
//! subset of these.
#![allow(dead_code)]

use std::fmt::Display;

use clap::ValueEnum;
use murk::image::ImageF32;
use murk::simulate::tof::TofSimFrame;
use murk::tof::{block_means, upsampled, SPEED_OF_LIGHT_M_PER_S};

/// Parses a seed list: `4`, `0-5` (inclusive), or a comma-separated mix such as `0-2,7,9`.
pub fn parse_seeds(text: &str) -> Result<Vec<u64>, String> {
    let mut seeds = Vec::new();
    for part in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        match part.split_once('-') {
            Some((lo, hi)) => {
                let lo: u64 = lo.trim().parse().map_err(|e| format!("`{part}`: {e}"))?;
                let hi: u64 = hi.trim().parse().map_err(|e| format!("`{part}`: {e}"))?;
                if hi < lo {
                    return Err(format!("`{part}`: the range is empty"));
                }
                seeds.extend(lo..=hi);
            }
            None => seeds.push(part.parse().map_err(|e| format!("`{part}`: {e}"))?),
        }
    }
    if seeds.is_empty() {
        return Err("no seeds given".into());
    }
    Ok(seeds)
}

/// A Markdown table printed to stdout, so a survey's output pastes into the docs as it is.
pub struct Table {
    header: Vec<String>,
    rows: Vec<Vec<String>>,
}

impl Table {
    /// A table with these column headings.
    pub fn new<S: Display>(header: &[S]) -> Self {
        Self {
            header: header.iter().map(ToString::to_string).collect(),
            rows: Vec::new(),
        }
    }

    /// Appends a row; it must have one cell per column.
    pub fn row<S: Display>(&mut self, cells: &[S]) {
        assert_eq!(cells.len(), self.header.len(), "one cell per column");
        self.rows
            .push(cells.iter().map(ToString::to_string).collect());
    }

    /// Prints the table as Markdown.
    pub fn print(&self) {
        let line = |cells: &[String]| println!("| {} |", cells.join(" | "));
        line(&self.header);
        println!("|{}", " --- |".repeat(self.header.len()));
        for r in &self.rows {
            line(r);
        }
    }
}

/// Arithmetic mean; NaN for an empty slice.
pub fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len() as f64
}

/// Image size of the simulated frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Size {
    /// 128 × 106: a quarter of the Kinect v2's sides, the same field of view.
    Reduced,
    /// 256 × 212: half the Kinect v2's sides.
    Half,
    /// 512 × 424, the Kinect v2's depth camera.
    Full,
}

impl Size {
    /// Width and height, pixels.
    pub fn dims(self) -> (usize, usize) {
        match self {
            Size::Reduced => (128, 106),
            Size::Half => (256, 212),
            Size::Full => (512, 424),
        }
    }
}

/// Range along the unit ray `d` of a surface whose optical path light → surface → camera is
/// `path_m`, for the emitter at `light` (camera frame, metres): the inversion the pipeline
/// applies, so the floor is scored with the same geometry as the estimate.
pub fn range_from_path(path_m: f64, d: [f64; 3], light: [f64; 3]) -> f64 {
    let l2 = light.iter().map(|v| v * v).sum::<f64>();
    let dl = d.iter().zip(&light).map(|(a, b)| a * b).sum::<f64>();
    if path_m * path_m <= l2 || path_m <= dl {
        return 0.5 * path_m;
    }
    (path_m * path_m - l2) / (2.0 * (path_m - dl))
}

/// A scattering phasor per pixel, row-major: real and imaginary parts.
pub struct Phasor {
    /// Width, pixels.
    pub w: usize,
    /// Height, pixels.
    pub h: usize,
    /// Real parts.
    pub re: Vec<f64>,
    /// Imaginary parts.
    pub im: Vec<f64>,
}

impl Phasor {
    /// The phasor of an amplitude and a phase image (radians).
    pub fn from_polar(amplitude: &ImageF32, phase: &ImageF32) -> Self {
        let (w, h) = amplitude.dims();
        let (re, im) = amplitude
            .data()
            .iter()
            .zip(phase.data())
            .map(|(&a, &p)| {
                let (s, c) = f64::from(p).sin_cos();
                (f64::from(a) * c, f64::from(a) * s)
            })
            .unzip();
        Self { w, h, re, im }
    }

    /// The means of `k × k` blocks ([`murk::tof::block_means`]; errors name `factor` unless
    /// `k` divides both sides).
    pub fn block_means(&self, k: usize) -> murk::Result<Self> {
        Ok(Self {
            w: self.w / k.max(1),
            h: self.h / k.max(1),
            re: block_means(&self.re, self.w, self.h, k)?,
            im: block_means(&self.im, self.w, self.h, k)?,
        })
    }

    /// Bilinear interpolation of a grid `k` times coarser back to the frame
    /// ([`murk::tof::upsampled`]; errors name `factor` or `values`).
    pub fn upsampled(&self, k: usize) -> murk::Result<Self> {
        Ok(Self {
            w: self.w * k,
            h: self.h * k,
            re: upsampled(&self.re, self.w, self.h, k)?,
            im: upsampled(&self.im, self.w, self.h, k)?,
        })
    }

    /// Amplitude and phase images (phase in `[0, 2π)`).
    pub fn to_polar(&self) -> (ImageF32, ImageF32) {
        let amplitude = self
            .re
            .iter()
            .zip(&self.im)
            .map(|(r, i)| r.hypot(*i) as f32);
        let phase = self
            .re
            .iter()
            .zip(&self.im)
            .map(|(r, i)| i.atan2(*r).rem_euclid(std::f64::consts::TAU) as f32);
        (
            ImageF32::from_vec(self.w, self.h, 1, amplitude.collect()).expect("sizes match"),
            ImageF32::from_vec(self.w, self.h, 1, phase.collect()).expect("sizes match"),
        )
    }
}

/// Mean |range − true range| (metres) over the ground-truth mask when `scatter` is subtracted
/// from the frame's `observed` phasor; NaN when no object is in view.
pub fn range_error(frame: &TofSimFrame, observed: &Phasor, scatter: &Phasor) -> f64 {
    let light = frame.config.light_position_m();
    let path_per_rad = SPEED_OF_LIGHT_M_PER_S
        / (2.0 * std::f64::consts::PI * frame.config.modulation_frequency_hz);
    let (mut sum, mut n) = (0.0, 0usize);
    for (i, &g) in frame.gt_mask.data().iter().enumerate() {
        if g < 0.5 {
            continue;
        }
        let phase = (observed.im[i] - scatter.im[i])
            .atan2(observed.re[i] - scatter.re[i])
            .rem_euclid(std::f64::consts::TAU);
        let d = frame
            .intrinsics
            .ray((i % observed.w) as f64, (i / observed.w) as f64);
        let range = range_from_path(phase * path_per_rad, d.into(), light);
        sum += (range - f64::from(frame.gt_range_m.data()[i])).abs();
        n += 1;
    }
    if n == 0 {
        f64::NAN
    } else {
        sum / n as f64
    }
}
