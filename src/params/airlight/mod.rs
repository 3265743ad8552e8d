//! Airlight estimators: the colour of the haze at infinite distance, `A` of Eq. 3.3, as one
//! achromatic scalar in `(0, 1]` (the reference's setting).

mod dark_channel;

pub use dark_channel::{dark_channel, dark_channel_airlight, DarkChannelParams};

use crate::error::Result;
use crate::image::ImageF32;

/// The airlight estimator a server is configured with.
#[derive(Clone, Debug)]
pub enum AirlightEstimator {
    /// The dark-channel rule.
    DarkChannel(DarkChannelParams),
}

impl Default for AirlightEstimator {
    fn default() -> Self {
        AirlightEstimator::DarkChannel(DarkChannelParams::default())
    }
}

impl AirlightEstimator {
    /// Grey airlight of `image`.
    pub fn estimate(&self, image: &ImageF32) -> Result<f32> {
        match self {
            AirlightEstimator::DarkChannel(p) => dark_channel_airlight(image, p),
        }
    }
}
