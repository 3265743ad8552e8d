//! `--outputs` and `--encoding`: which result images `murk tof` and `murk stereo` fetch, and how
//! they travel. The files written are the images fetched; by default every image, exact.

use clap::{Args, ValueEnum};

use murk_server::service::convert::OutputField;
use murk_server::service::proto::v1 as pb;

/// The wire encoding of result images, as named on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum EncodingArg {
    /// Raw float32: exact.
    F32,
    /// Raw float16: half the bytes, relative error at most 2^-11.
    F16,
    /// Lossless 16-bit PNG of the quantised values: metres in 1 mm steps, [0, 1] images in
    /// steps of 1/65535.
    Png,
}

/// Output selection flags.
#[derive(Args, Debug, Clone)]
pub struct OutputFlags {
    /// Result images to fetch and write, comma-separated, by their names in the result
    /// (e.g. z_depth_m,mask,range_std_m), and `points` for points.ply; default: all of them.
    #[arg(long, value_delimiter = ',')]
    pub outputs: Vec<String>,
    /// How the result images travel from the server.
    #[arg(long, value_enum, default_value_t = EncodingArg::F32)]
    pub encoding: EncodingArg,
}

impl OutputFlags {
    /// Whether points are wanted (`points` named, or nothing named), and the request's
    /// `outputs` for the images.
    pub fn split_points(
        &self,
        catalog: &[OutputField],
    ) -> anyhow::Result<(bool, pb::OutputOptions)> {
        let images: Vec<String> = self
            .outputs
            .iter()
            .filter(|f| *f != "points")
            .cloned()
            .collect();
        if images.is_empty() && !self.outputs.is_empty() {
            anyhow::bail!("--outputs names no image besides points: name at least one");
        }
        let wants_points = self.outputs.is_empty() || images.len() < self.outputs.len();
        let flags = OutputFlags {
            outputs: images,
            encoding: self.encoding,
        };
        Ok((wants_points, flags.wire(catalog)))
    }

    /// The request's `outputs`, every field of `catalog` written out when none was named (a
    /// session's unset selection would mean its compact default).
    pub fn wire(&self, catalog: &[OutputField]) -> pb::OutputOptions {
        let fields = if self.outputs.is_empty() {
            catalog.iter().map(|f| f.name.to_string()).collect()
        } else {
            self.outputs.clone()
        };
        pb::OutputOptions {
            fields,
            encoding: match self.encoding {
                EncodingArg::F32 => pb::ImageEncoding::F32,
                EncodingArg::F16 => pb::ImageEncoding::F16,
                EncodingArg::Png => pb::ImageEncoding::Png,
            } as i32,
        }
    }
}
