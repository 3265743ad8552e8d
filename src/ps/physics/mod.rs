//! Single-scattering physics of Sun et al. used by Ch. 4 (isotropic phase function, homogeneous
//! medium, near point sources).
