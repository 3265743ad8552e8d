//! Scattering-parameter estimation (reference Ch. 3.3): the airlight `A` of a hazy image
//! ([`airlight`]) and the scattering coefficient `β`, found by Algorithm 1 so that the dense
//! MVS depth agrees with a sparse SfM point cloud.

pub mod airlight;
pub mod joint_fit;
pub mod point_ratio;
pub mod residual;
pub mod search;
pub mod sparse;

#[cfg(test)]
mod tests;
