//! Airlight estimators: the colour of the haze at infinite distance, `A` of Eq. 3.3, as one
//! achromatic scalar in `(0, 1]` (the reference's setting).

mod dark_channel;

pub use dark_channel::{dark_channel, dark_channel_airlight, DarkChannelParams};
