//! Writing result images. As OpenEXR: murk's encoding (run-length, [`murk::io::encode_exr`])
//! against ZIP (deflate over 16 scan lines, the `exr` crate's `SMALL_LOSSLESS`), on the images a
//! streaming client writes every frame: a simulated 512×424 medium-fog ToF frame's results and a
//! simulated hazy 640×480 rectified pair's. Each image's size in both encodings is printed
//! before the timings. As a preview: the stereo depth coloured by [`murk::io::colorize`] (a
//! table of Turbo) against [`murk::io::turbo`] evaluated at every pixel.
//!
//! ```sh
//! cargo bench -p murk --bench io
//! ```

use std::io::Cursor;

use criterion::{criterion_group, criterion_main, Criterion};
use exr::prelude::{
    AnyChannel, AnyChannels, Encoding, FlatSamples, Image, Layer, LayerAttributes, SmallVec,
    WritableImage,
};

use murk::atmosphere::AtmosphereParams;
use murk::image::ImageF32;
use murk::io::{colorize, encode_exr, preview_range, turbo};
use murk::mvs::{estimate_rectified, CostKind, DehazingOptions, RectifiedOptions, RectifiedRig};
use murk::simulate::mvs::MvsSimConfig;
use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig};
use murk::simulate::{StereoMotion, StereoSequence};
use murk::tof::{estimate_tof_depth, TofInput, TofParams};
use murk::Monitor;

/// A one-channel image as ZIP-compressed OpenEXR (the channel named `Y`, as murk names it).
fn encode_zip(img: &ImageF32) -> Vec<u8> {
    let channel = AnyChannel::new("Y", FlatSamples::F32(img.channel(0).into_vec()));
    let layer = Layer::new(
        (img.width(), img.height()),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(SmallVec::from_vec(vec![channel])),
    );
    let mut out = Cursor::new(Vec::new());
    Image::from_layer(layer)
        .write()
        .non_parallel()
        .to_buffered(&mut out)
        .expect("encode");
    out.into_inner()
}

/// The images of one simulated ToF frame and one simulated stereo pair, by name.
fn results() -> Vec<(String, ImageF32)> {
    let noop = Monitor::noop();
    let cfg = TofSimConfig {
        preset: FogPreset::Medium,
        seed: 1,
        ..TofSimConfig::with_size(512, 424)
    };
    let f = simulate_tof(&cfg, &noop).expect("simulate");
    let input = TofInput {
        amplitude: f.amplitude,
        phase: f.phase,
        intrinsics: Some(f.intrinsics),
    };
    let tof = estimate_tof_depth(&input, &TofParams::default(), &noop).expect("ToF");

    // The rig's first pair (the same pair as `simulate_mvs` renders), with the true A and β.
    let rig = StereoSequence::new(&MvsSimConfig::with_size(640, 480), &StereoMotion::default())
        .expect("simulate");
    let pair = rig.frame(0, &noop).expect("simulate");
    let options = RectifiedOptions {
        cost: CostKind::DehazingWith(
            AtmosphereParams {
                airlight: rig.airlight,
                beta: rig.beta,
            },
            DehazingOptions::default(),
        ),
        ..RectifiedOptions::default()
    };
    let calibration = RectifiedRig::new(rig.intrinsics(), rig.baseline());
    let pair =
        estimate_rectified(&pair.left, &pair.right, &calibration, &options, &noop).expect("stereo");

    vec![
        ("tof_range_m".into(), tof.range_m),
        ("tof_range_std_m".into(), tof.range_std_m),
        ("tof_mask".into(), tof.mask),
        ("tof_corrected_amplitude".into(), tof.corrected_amplitude),
        ("stereo_depth".into(), pair.depth.z_depth),
        ("stereo_disparity".into(), pair.disparity),
        ("stereo_confidence".into(), pair.depth.confidence),
    ]
}

fn bench(c: &mut Criterion) {
    let images = results();
    for (name, img) in &images {
        let raw = img.pixel_count() * 4;
        let (rle, zip) = (
            encode_exr(img).expect("encode").len(),
            encode_zip(img).len(),
        );
        eprintln!(
            "{name}: {}x{}, RLE {rle} bytes, ZIP {zip} bytes ({:.1} % smaller), raw {raw}",
            img.width(),
            img.height(),
            100.0 * (1.0 - zip as f64 / rle as f64),
        );
    }
    let mut g = c.benchmark_group("exr_write");
    for (name, img) in &images {
        g.bench_function(format!("{name}_rle"), |b| {
            b.iter(|| encode_exr(img).expect("encode"))
        });
        g.bench_function(format!("{name}_zip"), |b| b.iter(|| encode_zip(img)));
    }
    g.finish();

    let depth = &images
        .iter()
        .find(|(name, _)| name == "stereo_depth")
        .expect("the stereo depth")
        .1;
    let (lo, hi) = preview_range(depth, None);
    let mut g = c.benchmark_group("preview_640x480");
    g.bench_function("colorize", |b| b.iter(|| colorize(depth, lo, hi, None)));
    g.bench_function("turbo_per_pixel", |b| {
        b.iter(|| {
            depth
                .data()
                .iter()
                .flat_map(|&v| turbo((v - lo) / (hi - lo)))
                .collect::<Vec<u8>>()
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
