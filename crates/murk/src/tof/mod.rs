//! Time-of-flight depth in fog (reference Ch. 5): estimate the scattering component of a CW-ToF
//! camera's amplitude and phase images by robust IRLS, segment the object as the outliers, and
//! recover the direct component's depth.
//!
//! Entry point: [`estimate_tof_depth`]. Building blocks, one idea per module: Tukey's biweight
//! and MAD scale ([`tukey`]), the local quadratic prior ([`quadratic_prior`]), the flip rows of
//! the symmetry prior ([`symmetry`]), the weighted least-squares x-step ([`wls`]), Algorithm 2
//! ([`irls`], its coarse level and held-out check in `coarse_level`, their settings and
//! convergence test in `irls_settings`) and its check for thin, dim object parts
//! ([`coherent`]), the mask's uncertain pixels beside the objects ([`ambiguous`]), the
//! bilateral pre-filter ([`bilateral`]), the pipeline ([`pipeline`]), a stream's frames from
//! the previous one's answer ([`TofTracker`]), on a coarser grid
//! ([`estimate_tof_depth_on_grid`]), and from scratch with the coarse level on that grid
//! (`grid_coarse`).

pub mod ambiguous;
pub mod bilateral;
mod coarse_level;
pub mod coarse_space;
pub mod coherent;
mod grid;
mod grid_coarse;
pub mod irls;
mod irls_settings;
pub mod multigrid;
pub mod noise_model;
mod params;
pub mod pipeline;
mod points;
pub mod quadratic_prior;
pub mod symmetry;
mod tracker;
pub mod tukey;
pub mod wls;

pub use grid::{block_means, estimate_tof_depth_on_grid, upsampled};
pub use irls::IrlsStart;
pub use params::*;
pub use pipeline::{
    estimate_tof_depth, estimate_tof_depth_from, estimate_tof_depth_with_solver,
    unmeasured_range_std_m,
};
pub use points::{measured_points, DEFAULT_MAX_POINT_RANGE_STD_M};
pub use tracker::{TofStart, TofTracker, TrackedTof, MAX_SCATTER_GRID, MIN_GRID_SIDE};
pub use wls::{Preconditioner, XStepSolver};
