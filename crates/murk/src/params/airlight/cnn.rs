//! The learned airlight estimator of reference Table 3.1, §3.3.1: six stride-2 convolutions
//! (each followed by batch normalisation and ReLU), global average pooling and two 1×1
//! convolutions that regress the achromatic airlight `A` of one hazy RGB image.
//!
//! The network runs on burn's pure-Rust CPU backend (`flex`). Its input is the image resampled
//! by area averaging to a fixed [`INPUT_WIDTH`]×[`INPUT_HEIGHT`]: `A` is a global quantity (the
//! colour of the haze at infinite distance), so it survives the downsampling, and a fixed size
//! keeps the receptive field of conv6 and the statistics the batch norms learnt the same for
//! every caller. The committed weights (`crates/murk/models/airlight_cnn.bpk`, burnpack format)
//! are compiled into the library by [`AirlightCnn::embedded`].

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, PaddingConfig2d};
use burn::store::ModuleRecord;
use burn::tensor::activation::relu;
use burn::tensor::{Bytes, Device, Tensor, TensorData};

use crate::error::{MurkError, Result};
use crate::image::ImageF32;

/// Width of the network input, pixels (a 256×192 image is averaged over 2×2 blocks).
pub const INPUT_WIDTH: usize = 128;
/// Height of the network input, pixels.
pub const INPUT_HEIGHT: usize = 96;

/// Field named by every error about the weights file.
const WEIGHTS_FIELD: &str = "airlight_weights";

/// The committed weights, trained by `murk train airlight` (see `docs/airlight.md`).
static EMBEDDED_WEIGHTS: &[u8] = include_bytes!("../../../models/airlight_cnn.bpk");

/// Kernel sizes and channel counts of conv1…conv6 (reference Table 3.1; all stride 2).
const CONV_LAYERS: [(usize, usize, usize); 6] = [
    (7, 3, 16),
    (5, 16, 32),
    (3, 32, 64),
    (3, 64, 128),
    (3, 128, 256),
    (3, 256, 256),
];

/// Convolution, batch normalisation, ReLU: every layer of Table 3.1 but conv8.
#[derive(Module, Debug)]
pub(crate) struct ConvBnRelu {
    pub(crate) conv: Conv2d,
    pub(crate) bn: BatchNorm,
}

impl ConvBnRelu {
    /// `k×k` kernel, `stride`, "same"-style symmetric padding `k/2` (the output is
    /// `⌈input / stride⌉` for odd `k`).
    fn new(k: usize, c_in: usize, c_out: usize, stride: usize, device: &Device) -> Self {
        let p = k / 2;
        Self {
            conv: Conv2dConfig::new([c_in, c_out], [k, k])
                .with_stride([stride, stride])
                .with_padding(PaddingConfig2d::Explicit(p, p, p, p))
                .init(device),
            bn: BatchNormConfig::new(c_out).init(device),
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        relu(self.bn.forward(self.conv.forward(x)))
    }
}

/// The network of reference Table 3.1 (burn module; training and inference share it).
#[derive(Module, Debug)]
pub(crate) struct AirlightNet {
    /// conv1…conv6, stride 2.
    pub(crate) features: Vec<ConvBnRelu>,
    /// conv7: 1×1, 256 → 64, with BN and ReLU.
    pub(crate) conv7: ConvBnRelu,
    /// conv8: 1×1, 64 → 1, no BN, no ReLU.
    pub(crate) conv8: Conv2d,
}

/// Initial bias of conv8: the middle of the reference's training range of `A`, [0.7, 1.0], so
/// the freshly initialised network starts near a typical answer instead of 0 (initialisation
/// only; the architecture is the reference's). Kept at 0.85 with murk's wider range [0.4, 1.0]:
/// the committed weights were trained from it.
pub(crate) const CONV8_BIAS_INIT: f32 = 0.85;

impl AirlightNet {
    /// Randomly initialised network (burn's default Kaiming-uniform convolutions; the device's
    /// RNG, seed it first for reproducibility).
    pub(crate) fn new(device: &Device) -> Self {
        let features = CONV_LAYERS
            .iter()
            .map(|&(k, c_in, c_out)| ConvBnRelu::new(k, c_in, c_out, 2, device))
            .collect();
        let mut conv8 = Conv2dConfig::new([64, 1], [1, 1]).init(device);
        conv8.bias = Some(burn::module::Param::from_tensor(Tensor::full(
            [1],
            CONV8_BIAS_INIT,
            device,
        )));
        Self {
            features,
            conv7: ConvBnRelu::new(1, 256, 64, 1, device),
            conv8,
        }
    }

    /// `[N, 3, H, W]` → `[N]` airlight estimates (unclamped).
    pub(crate) fn forward(&self, x: Tensor<4>) -> Tensor<1> {
        let mut x = x;
        for layer in &self.features {
            x = layer.forward(x);
        }
        // Global average pooling to [N, 256, 1, 1].
        let x = x.mean_dim(3).mean_dim(2);
        let x = self.conv8.forward(self.conv7.forward(x));
        let [n, _, _, _] = x.dims();
        x.reshape([n])
    }
}

/// Area-averaging resampling of an image to `out_w × out_h` (each output pixel is the mean of
/// the input area it covers, fractional overlaps weighted): the anti-aliased way to shrink an
/// image, and for integer factors exactly block averaging.
pub(crate) fn area_resize(image: &ImageF32, out_w: usize, out_h: usize) -> ImageF32 {
    let (w, h) = image.dims();
    let c = image.channels();
    // Per output index: (first source index, weights over consecutive source indices).
    let weights = |n_in: usize, n_out: usize| -> Vec<(usize, Vec<f32>)> {
        let scale = n_in as f64 / n_out as f64;
        (0..n_out)
            .map(|o| {
                let lo = o as f64 * scale;
                let hi = (o + 1) as f64 * scale;
                let first = lo.floor() as usize;
                let last = ((hi.ceil() as usize).max(first + 1)).min(n_in);
                let ws = (first..last)
                    .map(|i| {
                        let overlap = (hi.min((i + 1) as f64) - lo.max(i as f64)).max(0.0);
                        (overlap / scale) as f32
                    })
                    .collect();
                (first, ws)
            })
            .collect()
    };
    let wx = weights(w, out_w);
    let wy = weights(h, out_h);
    let src = image.data();
    // Horizontal pass: h rows of out_w pixels.
    let mut rows = vec![0.0f32; h * out_w * c];
    for y in 0..h {
        for (ox, (first, ws)) in wx.iter().enumerate() {
            let dst = &mut rows[(y * out_w + ox) * c..(y * out_w + ox + 1) * c];
            for (j, &wgt) in ws.iter().enumerate() {
                let s = &src[(y * w + first + j) * c..(y * w + first + j + 1) * c];
                for ch in 0..c {
                    dst[ch] += wgt * s[ch];
                }
            }
        }
    }
    // Vertical pass.
    let mut out = vec![0.0f32; out_h * out_w * c];
    for (oy, (first, ws)) in wy.iter().enumerate() {
        for (j, &wgt) in ws.iter().enumerate() {
            let s = &rows[(first + j) * out_w * c..(first + j + 1) * out_w * c];
            let d = &mut out[oy * out_w * c..(oy + 1) * out_w * c];
            for (dv, sv) in d.iter_mut().zip(s) {
                *dv += wgt * sv;
            }
        }
    }
    ImageF32::from_vec(out_w, out_h, c, out).expect("output dimensions are positive")
}

/// Checks an RGB image and resamples it to the network input size. The result is what
/// [`images_to_tensor`] batches; training uses the same function so the two cannot drift apart.
pub(crate) fn network_input(image: &ImageF32) -> Result<ImageF32> {
    image.ensure_channels(3).map_err(|e| e.within("image"))?;
    image.ensure_finite().map_err(|e| e.within("image"))?;
    Ok(area_resize(image, INPUT_WIDTH, INPUT_HEIGHT))
}

/// Packs network-input images (all [`INPUT_WIDTH`]×[`INPUT_HEIGHT`]×3, interleaved) into an
/// `[N, 3, H, W]` tensor, centred by −0.5 so the first convolution sees zero-mean data.
pub(crate) fn images_to_tensor<'a>(
    images: impl ExactSizeIterator<Item = &'a ImageF32>,
    device: &Device,
) -> Tensor<4> {
    let n = images.len();
    let plane = INPUT_WIDTH * INPUT_HEIGHT;
    let mut data = vec![0.0f32; n * 3 * plane];
    for (i, img) in images.enumerate() {
        debug_assert_eq!(img.dims(), (INPUT_WIDTH, INPUT_HEIGHT));
        let base = i * 3 * plane;
        for (p, px) in img.data().chunks_exact(3).enumerate() {
            for ch in 0..3 {
                data[base + ch * plane + p] = px[ch] - 0.5;
            }
        }
    }
    Tensor::from_data(
        TensorData::new(data, [n, 3, INPUT_HEIGHT, INPUT_WIDTH]),
        device,
    )
}

/// Reads a float tensor back to the host.
pub(crate) fn tensor_to_vec<const D: usize>(t: Tensor<D>) -> Result<Vec<f32>> {
    t.into_data()
        .try_into_vec::<f32>()
        .map_err(|e| MurkError::Internal(format!("reading an airlight CNN tensor: {e:?}")))
}

fn weights_error(reason: impl std::fmt::Display) -> MurkError {
    MurkError::invalid(WEIGHTS_FIELD, reason.to_string())
}

/// The learned airlight estimator (reference Table 3.1, §3.3.1), inference only, `f32`, CPU.
///
/// `Send + Sync` (burn 0.22 tensors and modules are; checked by a test): share one
/// `Arc<AirlightCnn>` across rayon/tokio workers, which run forward passes concurrently without
/// a lock. The network is in inference mode, so a forward pass mutates nothing.
#[derive(Debug)]
pub struct AirlightCnn {
    net: AirlightNet,
    device: Device,
    /// SHA-256 (hex) of the weights file it was loaded from; empty for a network built in
    /// memory (training). Saving is not byte-stable, so this is the fingerprint of the source.
    digest: String,
}

impl AirlightCnn {
    /// Loads weights from a burnpack record in memory (what [`AirlightCnn::save_bytes`] and
    /// `murk train airlight` write). A truncated, corrupt or wrong-architecture blob is an
    /// `InvalidArgument` naming `airlight_weights`, never a panic.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        let device = Device::flex();
        let net = Self::net_from_bytes(bytes, &device)?;
        let mut cnn = Self::from_net(net, device);
        cnn.digest = {
            use sha2::{Digest, Sha256};
            hex::encode(Sha256::digest(bytes))
        };
        Ok(cnn)
    }

    /// Loads weights from a file (see [`AirlightCnn::from_bytes`]); a missing file is an `Io`
    /// error naming the path.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|e| MurkError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_bytes(&bytes).map_err(|e| match e {
            MurkError::InvalidArgument { field, reason } => MurkError::InvalidArgument {
                field,
                reason: format!("{}: {reason}", path.display()),
            },
            other => other,
        })
    }

    /// The weights committed under `models/` and compiled into the library, so the estimator
    /// works from any working directory.
    pub fn embedded() -> Result<Self> {
        Self::from_bytes(EMBEDDED_WEIGHTS)
    }

    /// Estimates the airlight `A` of one hazy RGB image in `[0, 1]`, clamped to `[1e-3, 1]` like
    /// the dark-channel estimator. Fails on a non-RGB image or a non-finite sample (field
    /// `image`), and with `Numerical` if the network's output is not finite.
    pub fn estimate(&self, image: &ImageF32) -> Result<f32> {
        let input = network_input(image)?;
        Ok(self.estimate_batch(std::slice::from_ref(&input))?[0])
    }

    /// Airlight of each image already resampled by [`network_input`], in one forward pass.
    pub(crate) fn estimate_batch(&self, inputs: &[ImageF32]) -> Result<Vec<f32>> {
        let x = images_to_tensor(inputs.iter(), &self.device);
        tensor_to_vec(self.net.forward(x))?
            .into_iter()
            .map(|a| {
                if a.is_finite() {
                    Ok(a.clamp(1e-3, 1.0))
                } else {
                    Err(MurkError::Numerical(format!(
                        "airlight CNN produced a non-finite output ({a})"
                    )))
                }
            })
            .collect()
    }

    /// The weights as a burnpack record (full precision), the format [`AirlightCnn::from_bytes`]
    /// reads.
    pub fn save_bytes(&self) -> Result<Vec<u8>> {
        net_to_bytes(self.net.clone())
    }

    /// SHA-256 (hex) of the weights file this network was loaded from (empty when it was built
    /// in memory): identifies the model in job ids and logs.
    pub fn digest(&self) -> &str {
        &self.digest
    }

    /// Number of trainable parameters (≈ 1.0 M for Table 3.1).
    pub fn num_params(&self) -> usize {
        self.net.num_params()
    }

    pub(crate) fn from_net(net: AirlightNet, device: Device) -> Self {
        // Inference mode: batch norms use their running statistics.
        Self {
            net: net.valid().to_device(&device),
            device,
            digest: String::new(),
        }
    }

    fn net_from_bytes(bytes: &[u8], device: &Device) -> Result<AirlightNet> {
        // burnpack parsing is fallible by design, but the blob may come from anywhere: a panic
        // deep in a decoder must still reach the caller as an error, so it is caught here.
        let loaded = catch_unwind(AssertUnwindSafe(|| {
            let record = ModuleRecord::from_bytes(Bytes::from_bytes_vec(bytes.to_vec()))
                .map_err(|e| weights_error(format!("not a burnpack record: {e}")))?
                // Stored f16/f64 weights would otherwise change the network's dtype.
                .cast_to_module_dtype();
            let net = AirlightNet::new(device)
                .try_load_record(record)
                .map_err(|e| weights_error(format!("does not fit the Table 3.1 network: {e}")))?;
            // Shapes are validated by the record; a final probe catches what is not (e.g. NaN
            // weights) before the estimator is handed out.
            let probe = net
                .valid()
                .forward(Tensor::zeros([1, 3, INPUT_HEIGHT, INPUT_WIDTH], device));
            let v = tensor_to_vec(probe)?;
            if v.len() != 1 || !v[0].is_finite() {
                return Err(weights_error(format!(
                    "the network's output on a grey image is not a finite scalar: {v:?}"
                )));
            }
            Ok(net)
        }));
        match loaded {
            Ok(r) => r,
            Err(_) => Err(weights_error("the record could not be decoded")),
        }
    }
}

/// Serialises a network as a burnpack record (full precision `f32`).
pub(crate) fn net_to_bytes(net: AirlightNet) -> Result<Vec<u8>> {
    let bytes = net
        .into_record()
        .into_bytes()
        .map_err(|e| MurkError::Internal(format!("serialising the airlight CNN: {e}")))?;
    Ok(bytes.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::Param;

    fn assert_send_sync<T: Send + Sync>() {}

    #[test]
    fn estimator_is_send_and_sync() {
        assert_send_sync::<AirlightCnn>();
        assert_send_sync::<AirlightNet>();
    }

    fn set_conv(conv: &mut Conv2d, w: f32, b: f32, device: &Device) {
        let shape = conv.weight.dims();
        conv.weight = Param::from_tensor(Tensor::full(shape, w, device));
        conv.bias = Some(Param::from_tensor(Tensor::full([shape[0]], b, device)));
    }

    #[test]
    fn conv_block_stride_and_padding_by_hand() {
        // Constant input v over 2 channels, 8×8; 3×3 kernel of constant w, stride 2, padding 1:
        // output (i, j) centres on (2i, 2j) and sees rows(i)·cols(j) valid taps per channel,
        // rows(0) = 2 (the top row is padding), rows(i ≥ 1) = 3. BN in eval mode with identity
        // statistics divides by √(1 + ε).
        let device = Device::flex();
        let mut block = ConvBnRelu::new(3, 2, 1, 2, &device);
        set_conv(&mut block.conv, 0.25, 0.5, &device);
        let block = block.valid();
        let v = 0.8f32;
        let out = block.forward(Tensor::full([1, 2, 8, 8], v, &device));
        assert_eq!(out.dims(), [1, 1, 4, 4]);
        let got = tensor_to_vec(out).unwrap();
        let norm = (1.0f32 + 1e-5).sqrt();
        for i in 0..4 {
            for j in 0..4 {
                let taps = |k: usize| if k == 0 { 2.0 } else { 3.0 };
                let expected = (2.0 * 0.25 * v * taps(i) * taps(j) + 0.5) / norm;
                let g = got[i * 4 + j];
                assert!((g - expected).abs() < 1e-5, "({i}, {j}): {g} vs {expected}");
            }
        }
    }

    #[test]
    fn whole_network_by_hand_shape_and_determinism() {
        // conv1…conv6 with zero weights and bias 0.1 output the constant relu(0.1/s) whatever
        // the input (s = √(1 + ε), eval-mode BN with identity statistics), so the pooled
        // feature is h6 = 0.1/s; conv7 (weights 0.01, bias 0.2) gives
        // h7 = (256·0.01·h6 + 0.2)/s, and conv8 (weights 0.05, bias 0.3) 64·0.05·h7 + 0.3.
        let device = Device::flex();
        let mut net = AirlightNet::new(&device);
        for layer in &mut net.features {
            set_conv(&mut layer.conv, 0.0, 0.1, &device);
        }
        set_conv(&mut net.conv7.conv, 0.01, 0.2, &device);
        set_conv(&mut net.conv8, 0.05, 0.3, &device);
        let s = (1.0f64 + 1e-5).sqrt();
        let h6 = 0.1 / s;
        let h7 = (256.0 * 0.01 * h6 + 0.2) / s;
        let expected = (64.0 * 0.05 * h7 + 0.3) as f32;
        let cnn = AirlightCnn::from_net(net, device);
        let img = ImageF32::filled(64, 40, 3, 0.3);
        let a = cnn.estimate(&img).unwrap();
        assert!((a - expected.min(1.0)).abs() < 1e-5, "{a} vs {expected}");
        // Raw (unclamped) output and batch shape.
        let input = network_input(&img).unwrap();
        let x = images_to_tensor([input.clone(), input].iter(), &cnn.device);
        let out = cnn.net.forward(x);
        assert_eq!(out.dims(), [2]);
        let raw = tensor_to_vec(out).unwrap();
        assert!(
            (raw[0] as f64 - (64.0 * 0.05 * h7 + 0.3)).abs() < 1e-5,
            "{raw:?}"
        );
        assert_eq!(raw[0], raw[1]);
        assert_eq!(cnn.estimate(&img).unwrap(), a, "deterministic");
    }

    #[test]
    fn architecture_matches_table_3_1() {
        let device = Device::flex();
        let net = AirlightNet::new(&device);
        let kernels: Vec<[usize; 4]> = net.features.iter().map(|l| l.conv.weight.dims()).collect();
        assert_eq!(
            kernels,
            vec![
                [16, 3, 7, 7],
                [32, 16, 5, 5],
                [64, 32, 3, 3],
                [128, 64, 3, 3],
                [256, 128, 3, 3],
                [256, 256, 3, 3]
            ]
        );
        assert_eq!(net.conv7.conv.weight.dims(), [64, 256, 1, 1]);
        assert_eq!(net.conv8.weight.dims(), [1, 64, 1, 1]);
        // Weights + biases + BN (γ, β) ≈ 1.0 M.
        let n = net.num_params();
        assert!((900_000..1_200_000).contains(&n), "{n} parameters");
    }

    #[test]
    fn weights_round_trip_bit_exactly() {
        let device = Device::flex();
        device.seed(7);
        let net = AirlightNet::new(&device);
        let a = AirlightCnn::from_net(net, device);
        let bytes = a.save_bytes().unwrap();
        let b = AirlightCnn::from_bytes(&bytes).unwrap();
        let img = ImageF32::from_vec(
            50,
            30,
            3,
            (0..50 * 30 * 3).map(|i| (i % 97) as f32 / 97.0).collect(),
        )
        .unwrap();
        let input = network_input(&img).unwrap();
        let ya = a.estimate_batch(std::slice::from_ref(&input)).unwrap();
        let yb = b.estimate_batch(std::slice::from_ref(&input)).unwrap();
        assert_eq!(ya, yb);
        // burnpack bytes are not canonical (two saves of the same weights differed), so the
        // round trip is checked on what matters: a second save/load gives the same outputs.
        let c = AirlightCnn::from_bytes(&b.save_bytes().unwrap()).unwrap();
        assert_eq!(c.estimate_batch(std::slice::from_ref(&input)).unwrap(), ya);
    }

    #[test]
    fn corrupt_or_truncated_weights_are_errors_not_panics() {
        let good = AirlightCnn::embedded().unwrap().save_bytes().unwrap();
        for bad in [
            Vec::new(),
            b"not a burnpack file".to_vec(),
            good[..good.len() / 2].to_vec(),
            good[..64].to_vec(),
        ] {
            let e = AirlightCnn::from_bytes(&bad).unwrap_err();
            assert_eq!(e.field(), Some(WEIGHTS_FIELD), "{e}");
        }
        // A valid record of another network: wrong shapes.
        let device = Device::flex();
        let other = ConvBnRelu::new(3, 3, 8, 2, &device);
        let other_bytes = other.into_record().into_bytes().unwrap().to_vec();
        let e = AirlightCnn::from_bytes(&other_bytes).unwrap_err();
        assert_eq!(e.field(), Some(WEIGHTS_FIELD), "{e}");
        let e = AirlightCnn::load("/nonexistent/airlight.bpk").unwrap_err();
        assert!(matches!(e, MurkError::Io { .. }), "{e}");
    }

    #[test]
    fn rejects_non_rgb_and_non_finite_images() {
        let cnn = AirlightCnn::embedded().unwrap();
        let grey = ImageF32::filled(16, 16, 1, 0.5);
        assert_eq!(cnn.estimate(&grey).unwrap_err().field(), Some("image"));
        let mut rgb = ImageF32::filled(16, 16, 3, 0.5);
        rgb.set(3, 4, 1, f32::INFINITY);
        assert_eq!(cnn.estimate(&rgb).unwrap_err().field(), Some("image"));
    }

    #[test]
    fn area_resize_averages_blocks_and_keeps_constants() {
        let img = ImageF32::from_fn(4, 2, |x, y| (x + 4 * y) as f32);
        let half = area_resize(&img, 2, 1);
        // Blocks {0,1,4,5} and {2,3,6,7}.
        assert_eq!(half.data(), &[2.5, 4.5]);
        let c = ImageF32::filled(37, 23, 3, 0.7);
        let r = area_resize(&c, 16, 12);
        assert!(r.data().iter().all(|v| (v - 0.7).abs() < 1e-6));
        let up = area_resize(&c, 50, 30);
        assert!(up.data().iter().all(|v| (v - 0.7).abs() < 1e-6));
    }

    fn textured(w: usize, h: usize) -> ImageF32 {
        ImageF32::from_vec(
            w,
            h,
            3,
            (0..w * h * 3)
                .map(|i| 0.4 + 0.5 * ((i % 89) as f32 / 89.0))
                .collect(),
        )
        .unwrap()
    }

    #[test]
    fn concurrent_estimates_match_serial() {
        // The server shares one estimator between workers without a lock.
        let cnn = std::sync::Arc::new(AirlightCnn::embedded().unwrap());
        let img = textured(96, 64);
        let serial = cnn.estimate(&img).unwrap();
        let handles: Vec<_> = (0..4)
            .map(|_| {
                let (c, i) = (cnn.clone(), img.clone());
                std::thread::spawn(move || c.estimate(&i).unwrap())
            })
            .collect();
        for h in handles {
            assert_eq!(h.join().unwrap(), serial);
        }
    }
}
