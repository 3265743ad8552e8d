//! The SfM tracks behind a sparse map: its world points and where each view saw them, from
//! which the poses' uncertainty is computed ([`super::pose_error`]).

use crate::error::{MurkError, Result};

/// One 2-D observation of an SfM point in one of the request's views.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    /// Index of the point in [`SfmTracks::points`].
    pub point: u32,
    /// The view: 0 = the reference, `1 + i` = source `i`.
    pub view: u32,
    /// Where SfM found the point in the view, pixels (murk's convention: the top-left pixel's
    /// centre at (0, 0)).
    pub pixel: [f64; 2],
}

/// The SfM points behind a sparse map, with where each view saw them: what the poses'
/// uncertainty is computed from.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SfmTracks {
    /// World points, scene units: the list the sparse map was made of.
    pub points: Vec<[f64; 3]>,
    /// Per point, its [`crate::params::sparse::SparseSample::seen_by`] mask; empty = seen by
    /// every source.
    pub seen_by: Vec<u32>,
    /// The points' observations in the reference and the sources.
    pub observations: Vec<Observation>,
}

impl SfmTracks {
    /// Checks the indices and coordinates against `views` views (the reference and its
    /// sources). Errors name `points[i]`, `seen_by` or `observations[i].…`.
    pub fn validate(&self, views: usize) -> Result<()> {
        if let Some(i) = self
            .points
            .iter()
            .position(|p| !p.iter().all(|c| c.is_finite()))
        {
            return Err(MurkError::invalid(
                format!("points[{i}]"),
                "coordinates must be finite",
            ));
        }
        if !self.seen_by.is_empty() && self.seen_by.len() != self.points.len() {
            return Err(MurkError::invalid(
                "seen_by",
                format!(
                    "one source mask per point or none: {} masks for {} points",
                    self.seen_by.len(),
                    self.points.len()
                ),
            ));
        }
        for (i, o) in self.observations.iter().enumerate() {
            if o.point as usize >= self.points.len() {
                return Err(MurkError::invalid(
                    format!("observations[{i}].point"),
                    format!("{} but there are {} points", o.point, self.points.len()),
                ));
            }
            if o.view as usize >= views {
                return Err(MurkError::invalid(
                    format!("observations[{i}].view"),
                    format!(
                        "{} but there are {views} views (0 = the reference, 1 + i = source i)",
                        o.view
                    ),
                ));
            }
            if !o.pixel.iter().all(|c| c.is_finite()) {
                return Err(MurkError::invalid(
                    format!("observations[{i}].pixel"),
                    format!("coordinates must be finite, got {:?}", o.pixel),
                ));
            }
        }
        Ok(())
    }
}
