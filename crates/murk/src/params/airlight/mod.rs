//! Airlight estimators: the colour of the haze at infinite distance, `A` of Eq. 3.3, as one
//! achromatic scalar in `(0, 1]` (the reference's setting).
//!
//! Two estimators: the classical dark-channel rule of He et al. ([`dark_channel_airlight`]) and
//! the learned CNN of reference Table 3.1, §3.3.1 (`AirlightCnn`, with the default feature
//! `airlight-cnn`); [`AirlightEstimator`] picks one at configuration time.

#[cfg(feature = "airlight-cnn")]
mod cnn;
mod dark_channel;
#[cfg(feature = "airlight-cnn")]
pub mod train;

use std::path::Path;
#[cfg(feature = "airlight-cnn")]
use std::sync::Arc;

#[cfg(feature = "airlight-cnn")]
pub use cnn::{AirlightCnn, INPUT_HEIGHT, INPUT_WIDTH};
pub use dark_channel::{dark_channel, dark_channel_airlight, DarkChannelParams};

use crate::error::Result;
use crate::image::ImageF32;

/// An airlight estimator chosen at configuration time; cheap to clone and `Send + Sync`.
#[derive(Clone, Debug)]
pub enum AirlightEstimator {
    /// The dark-channel prior's rule (He et al.).
    DarkChannel(DarkChannelParams),
    /// The learned estimator of reference Table 3.1, §3.3.1, shared between workers.
    #[cfg(feature = "airlight-cnn")]
    Cnn(Arc<AirlightCnn>),
}

impl AirlightEstimator {
    /// Airlight `A` of one hazy RGB image, in `(0, 1]`.
    pub fn estimate(&self, image: &ImageF32) -> Result<f32> {
        match self {
            AirlightEstimator::DarkChannel(p) => dark_channel_airlight(image, p),
            #[cfg(feature = "airlight-cnn")]
            AirlightEstimator::Cnn(cnn) => cnn.estimate(image),
        }
    }

    /// The CNN estimator with the weights at `weights`, or the weights compiled into murk when
    /// `None`. If loading fails: the error (field `airlight_weights`, or `Io` for an unreadable
    /// file) when `fallback_to_dark_channel` is false; otherwise a `tracing` warning and the
    /// dark-channel estimator with default parameters. Built without the `airlight-cnn`
    /// feature, there is no CNN to load: the error names `airlight_estimator`.
    pub fn from_config(weights: Option<&Path>, fallback_to_dark_channel: bool) -> Result<Self> {
        #[cfg(feature = "airlight-cnn")]
        let loaded = match weights {
            Some(path) => AirlightCnn::load(path).map(|cnn| AirlightEstimator::Cnn(Arc::new(cnn))),
            None => AirlightCnn::embedded().map(|cnn| AirlightEstimator::Cnn(Arc::new(cnn))),
        };
        #[cfg(not(feature = "airlight-cnn"))]
        let loaded: Result<Self> = Err(crate::error::MurkError::invalid(
            "airlight_estimator",
            "this build of murk has no airlight CNN (the `airlight-cnn` feature is off)",
        ));
        match loaded {
            Ok(estimator) => Ok(estimator),
            Err(e) if fallback_to_dark_channel => {
                tracing::warn!(
                    error = %e,
                    weights = ?weights,
                    "airlight CNN weights unusable; falling back to the dark-channel estimator"
                );
                Ok(AirlightEstimator::DarkChannel(DarkChannelParams::default()))
            }
            Err(e) => Err(e),
        }
    }

    /// Short name for logs and reports: `dark_channel` or `cnn`.
    pub fn name(&self) -> &'static str {
        match self {
            AirlightEstimator::DarkChannel(_) => "dark_channel",
            #[cfg(feature = "airlight-cnn")]
            AirlightEstimator::Cnn(_) => "cnn",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::mvs::{simulate_mvs, MvsSimConfig};
    use crate::Monitor;

    fn small_scene(seed: u64) -> (ImageF32, f32) {
        let cfg = MvsSimConfig {
            seed,
            num_views: 2,
            supersample: 1,
            ..MvsSimConfig::with_size(128, 96)
        };
        let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        (scene.views[scene.reference].hazy.clone(), scene.airlight)
    }

    #[cfg(feature = "airlight-cnn")]
    #[test]
    fn both_estimators_estimate_a_simulated_scene() {
        let cnn = AirlightEstimator::from_config(None, false).unwrap();
        assert_eq!(cnn.name(), "cnn");
        let dc = AirlightEstimator::DarkChannel(DarkChannelParams::default());
        // Seeds far from the training and held-out ranges of `murk train airlight`.
        for seed in [1_000_001, 1_000_002] {
            let (img, a) = small_scene(seed);
            let a_cnn = cnn.estimate(&img).unwrap();
            let a_dc = dc.estimate(&img).unwrap();
            assert!((a_cnn - a).abs() < 0.08, "cnn {a_cnn}, true {a}");
            assert!(a_dc > 0.0 && a_dc <= 1.0, "dark channel {a_dc}");
        }
    }

    #[cfg(feature = "airlight-cnn")]
    #[test]
    fn from_config_bad_path_errors_or_falls_back() {
        let missing = Path::new("/nonexistent/murk/airlight_cnn.bpk");
        assert!(AirlightEstimator::from_config(Some(missing), false).is_err());
        let fb = AirlightEstimator::from_config(Some(missing), true).unwrap();
        assert!(matches!(fb, AirlightEstimator::DarkChannel(_)));

        let dir = tempfile::tempdir().unwrap();
        let corrupt = dir.path().join("corrupt.bpk");
        std::fs::write(&corrupt, b"definitely not weights").unwrap();
        let e = AirlightEstimator::from_config(Some(&corrupt), false).unwrap_err();
        assert_eq!(e.field(), Some("airlight_weights"), "{e}");
        assert_eq!(
            AirlightEstimator::from_config(Some(&corrupt), true)
                .unwrap()
                .name(),
            "dark_channel"
        );

        // A good file loads.
        let good = dir.path().join("good.bpk");
        let bytes = AirlightCnn::embedded().unwrap().save_bytes().unwrap();
        std::fs::write(&good, bytes).unwrap();
        let est = AirlightEstimator::from_config(Some(&good), false).unwrap();
        assert_eq!(est.name(), "cnn");
    }

    #[cfg(not(feature = "airlight-cnn"))]
    #[test]
    fn without_the_cnn_the_config_errors_or_falls_back_to_the_dark_channel() {
        let e = AirlightEstimator::from_config(None, false).unwrap_err();
        assert_eq!(e.field(), Some("airlight_estimator"), "{e}");
        let fb = AirlightEstimator::from_config(None, true).unwrap();
        assert_eq!(fb.name(), "dark_channel");
        let (img, _) = small_scene(7);
        let a = fb.estimate(&img).unwrap();
        assert!(a > 0.0 && a <= 1.0, "{a}");
    }
}
