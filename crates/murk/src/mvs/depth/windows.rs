//! Plane windows: each group of rows searches its own run of the plane set instead of every
//! plane, where a prior (the previous frame of a stream) says which depths those rows hold.
//!
//! A robot's scene is layered by image row (floor near at the bottom, far walls at the
//! horizon), so the depths of a group of rows span much less than the image's: on a simulated
//! 640×480 rig moving through a room, 32-row groups span 19 pixels of disparity on average
//! against 44 for the whole image. The plane sweep, the window and SGM cost in proportion to the
//! planes searched, so a pixel's work follows the depths of its own rows.
//!
//! Within a group every pixel has the same planes, so the box window, the horizontal paths and
//! the downward paths inside the group run exactly as over a plane set of that length. Where a
//! downward path crosses into a group with another window, the previous row's path costs are
//! carried over for the planes both windows hold, and a plane the previous window lacked is
//! reached only by the path's jump (`min_k L(p−r, k) + P2`), as a plane with no good path cost
//! would be ([`super::sgm::OnePass::set_planes`]).

use std::ops::Range;

use crate::error::{MurkError, Result};

/// The planes each group of `group_rows` image rows searches: runs of a plane set's indices
/// (see the module documentation).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PlaneWindows {
    group_rows: usize,
    windows: Vec<Range<usize>>,
}

impl PlaneWindows {
    /// Windows for the groups of `group_rows` rows, from the top: `windows[g]` for rows
    /// `g·group_rows .. (g + 1)·group_rows`. Errors name `windows` when `group_rows` is 0, when
    /// a window is empty, or when there are no windows.
    pub fn new(group_rows: usize, windows: Vec<Range<usize>>) -> Result<Self> {
        if group_rows == 0 {
            return Err(MurkError::invalid(
                "windows",
                "group rows must be at least 1",
            ));
        }
        if windows.is_empty() {
            return Err(MurkError::invalid("windows", "no windows"));
        }
        if let Some((g, w)) = windows.iter().enumerate().find(|(_, w)| w.is_empty()) {
            return Err(MurkError::invalid(
                "windows",
                format!("group {g}'s window {w:?} holds no plane"),
            ));
        }
        Ok(Self {
            group_rows,
            windows,
        })
    }

    /// Every row searches the planes `0..num_planes` (the same work and depth as no windows).
    pub fn whole(num_planes: usize, height: usize) -> Result<Self> {
        Self::new(height.max(1), std::iter::once(0..num_planes).collect())
    }

    /// Rows per group.
    pub fn group_rows(&self) -> usize {
        self.group_rows
    }

    /// The groups' windows, from the top.
    pub fn windows(&self) -> &[Range<usize>] {
        &self.windows
    }

    /// The planes row `y` searches (rows below the last group take its window).
    pub fn of_row(&self, y: usize) -> Range<usize> {
        self.windows[self.group_of(y)].clone()
    }

    /// The first row after `y` whose group is not `y`'s (`usize::MAX` in the last group).
    pub fn group_end(&self, y: usize) -> usize {
        let g = self.group_of(y);
        if g + 1 == self.windows.len() {
            usize::MAX
        } else {
            (g + 1) * self.group_rows
        }
    }

    /// The most planes a row searches.
    pub fn max_len(&self) -> usize {
        self.windows.iter().map(|w| w.len()).max().unwrap_or(0)
    }

    /// Planes searched by an `h`-row image, summed over its rows: the work of the sweep and of
    /// SGM, against `h · num_planes` without windows.
    pub fn planes_searched(&self, h: usize) -> usize {
        (0..h).map(|y| self.of_row(y).len()).sum()
    }

    /// Checks the windows against a set of `num_planes` planes (every window inside it); errors
    /// name `windows`.
    pub fn validate(&self, num_planes: usize) -> Result<()> {
        match self
            .windows
            .iter()
            .enumerate()
            .find(|(_, w)| w.end > num_planes)
        {
            Some((g, w)) => Err(MurkError::invalid(
                "windows",
                format!("group {g}'s window {w:?} reaches past the {num_planes} planes"),
            )),
            None => Ok(()),
        }
    }

    fn group_of(&self, y: usize) -> usize {
        (y / self.group_rows).min(self.windows.len() - 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_take_their_groups_window_and_the_last_group_extends() {
        let p = PlaneWindows::new(4, vec![2..10, 0..5, 7..9]).unwrap();
        assert_eq!(p.of_row(0), 2..10);
        assert_eq!(p.of_row(3), 2..10);
        assert_eq!(p.of_row(4), 0..5);
        assert_eq!(p.of_row(8), 7..9);
        assert_eq!(p.of_row(100), 7..9);
        assert_eq!(p.group_end(1), 4);
        assert_eq!(p.group_end(5), 8);
        assert_eq!(p.group_end(9), usize::MAX);
        assert_eq!(p.max_len(), 8);
        assert_eq!(p.planes_searched(10), 4 * 8 + 4 * 5 + 2 * 2);
        assert!(p.validate(10).is_ok());
        assert!(p.validate(9).is_err());
    }

    #[test]
    fn bad_windows_are_refused_naming_the_field() {
        for bad in [
            PlaneWindows::new(0, std::iter::once(0..3).collect()),
            PlaneWindows::new(4, vec![]),
            PlaneWindows::new(4, vec![0..3, 2..2]),
        ] {
            let e = bad.unwrap_err().to_string();
            assert!(e.contains("windows"), "{e}");
        }
    }
}
