//! Sensor frames out of a bag: the two image topics of a frame paired by stamp, each with the
//! latest `CameraInfo` of its camera. A frame whose camera has not yet published its
//! `CameraInfo` waits for it (a few frames at most); one that never gets it is an error.

use std::collections::{HashMap, VecDeque};

use super::cdr;
use super::images::RosImage;
use super::msgs::{CameraInfo, CompressedImage, Header, Image};
use super::pairing::{Side, StampPairer};
use super::reader::{BagMessage, BagReader};
use super::BagError;

/// Frames a camera may wait for its first `CameraInfo` before the bag is taken to have none.
const MAX_WAITING_FOR_INFO: usize = 16;

/// Which topics make a frame.
#[derive(Debug, Clone)]
pub struct FramePlan {
    /// The two image topics (left and right; amplitude and phase).
    pub images: [String; 2],
    /// The `CameraInfo` topic of each image topic (the same one twice for one camera).
    pub infos: [String; 2],
    /// Largest difference of the two images' stamps in a pair, nanoseconds.
    pub tolerance_ns: u64,
    /// Keep the input messages with each frame, to copy them to the output.
    pub keep_inputs: bool,
}

impl FramePlan {
    /// Every topic the plan reads.
    pub fn topics(&self) -> Vec<String> {
        let mut t: Vec<String> = self.images.iter().chain(&self.infos).cloned().collect();
        t.dedup();
        t
    }
}

/// One frame of a bag.
#[derive(Debug)]
pub struct BagFrame {
    /// The first image's header (its stamp and frame_id are the results').
    pub header: Header,
    /// When the first image was logged, nanoseconds.
    pub log_time: u64,
    /// The two images.
    pub images: [RosImage; 2],
    /// Each image's camera.
    pub infos: [CameraInfo; 2],
    /// The input messages since the previous frame (with [`FramePlan::keep_inputs`]).
    pub inputs: Vec<BagMessage>,
}

type Waiting = (RosImage, BagMessage);

/// Reads frames from a bag; messages it gives up on are listed by [`BagFrames::take_skipped`].
pub struct BagFrames {
    reader: BagReader,
    plan: FramePlan,
    pairer: StampPairer<Waiting>,
    infos: HashMap<String, CameraInfo>,
    waiting: VecDeque<(Waiting, Waiting)>,
    ready: VecDeque<BagFrame>,
    inputs: Vec<BagMessage>,
    skipped: Vec<String>,
    ended: bool,
}

impl BagFrames {
    /// Frames of `reader`'s bag as `plan` says; the reader must read the plan's topics.
    pub fn new(reader: BagReader, plan: FramePlan) -> Self {
        Self {
            reader,
            pairer: StampPairer::new(plan.tolerance_ns, 64),
            plan,
            infos: HashMap::new(),
            waiting: VecDeque::new(),
            ready: VecDeque::new(),
            inputs: Vec::new(),
            skipped: Vec::new(),
            ended: false,
        }
    }

    /// Bytes of the bag read so far, and its length.
    pub fn progress(&self) -> (u64, u64) {
        self.reader.progress()
    }

    /// Why messages were skipped since the last call, one line each.
    pub fn take_skipped(&mut self) -> Vec<String> {
        std::mem::take(&mut self.skipped)
    }

    fn note_unpaired(&mut self, unpaired: Vec<super::pairing::Unpaired>) {
        for u in unpaired {
            let (topic, other) = match u.side {
                Side::First => (&self.plan.images[0], &self.plan.images[1]),
                Side::Second => (&self.plan.images[1], &self.plan.images[0]),
            };
            self.skipped.push(format!(
                "{topic} at {}: no message on {other} within {:.3} ms of its stamp",
                display_ns(u.stamp_ns),
                self.plan.tolerance_ns as f64 * 1e-6
            ));
        }
    }

    /// Moves waiting pairs whose cameras both have a `CameraInfo` to `ready`.
    fn release(&mut self) {
        if !self.plan.infos.iter().all(|t| self.infos.contains_key(t)) {
            return;
        }
        while let Some(((a, am), (b, bm))) = self.waiting.pop_front() {
            let mut inputs = std::mem::take(&mut self.inputs);
            if self.plan.keep_inputs {
                inputs.push(am.clone());
                inputs.push(bm);
            }
            self.ready.push_back(BagFrame {
                header: a.header().clone(),
                log_time: am.log_time,
                infos: [
                    self.infos[&self.plan.infos[0]].clone(),
                    self.infos[&self.plan.infos[1]].clone(),
                ],
                images: [a, b],
                inputs,
            });
        }
    }

    fn missing_info(&self) -> Option<BagError> {
        let ((a, _), _) = self.waiting.front()?;
        let (i, info) = self
            .plan
            .infos
            .iter()
            .enumerate()
            .find(|(_, t)| !self.infos.contains_key(*t))?;
        Some(BagError::MissingCameraInfo {
            info_topic: info.clone(),
            image_topic: self.plan.images[i].clone(),
            stamp: a.header().stamp.display(),
        })
    }

    fn take(&mut self, msg: BagMessage) -> Result<(), BagError> {
        let topic = msg.topic.name.clone();
        let at = || format!("logged at {}", display_ns(msg.log_time));
        if msg.topic.message_encoding != "cdr" {
            return Err(BagError::Message {
                topic: topic.clone(),
                at: at(),
                message: format!(
                    "message encoding `{}`: murk reads ROS 2 bags, whose messages are CDR",
                    msg.topic.message_encoding
                ),
            });
        }
        let schema = msg.topic.schema.as_ref().map_or("", |s| s.name.as_str());
        let side = self.plan.images.iter().position(|t| *t == topic);
        let bad = |message: String| BagError::Message {
            topic: topic.clone(),
            at: at(),
            message,
        };
        let Some(side) = side else {
            // A CameraInfo topic.
            if schema != "sensor_msgs/msg/CameraInfo" {
                return Err(bad(format!(
                    "schema `{schema}`, where sensor_msgs/msg/CameraInfo was expected"
                )));
            }
            let info: CameraInfo = cdr::decode(&msg.data).map_err(bad)?;
            if self.plan.keep_inputs {
                self.inputs.push(msg);
            }
            self.infos.insert(topic, info);
            self.release();
            return Ok(());
        };
        let image = match schema {
            "sensor_msgs/msg/Image" => RosImage::Raw(cdr::decode::<Image>(&msg.data).map_err(bad)?),
            "sensor_msgs/msg/CompressedImage" => {
                RosImage::Compressed(cdr::decode::<CompressedImage>(&msg.data).map_err(bad)?)
            }
            other => {
                return Err(bad(format!(
                    "schema `{other}`: an image topic carries sensor_msgs/msg/Image or \
                     sensor_msgs/msg/CompressedImage"
                )))
            }
        };
        let stamp = image.header().stamp.as_nanos();
        let side = if side == 0 { Side::First } else { Side::Second };
        let pair = self.pairer.push(side, stamp, (image, msg));
        let unpaired = self.pairer.take_unpaired();
        self.note_unpaired(unpaired);
        if let Some((a, b, _)) = pair {
            self.waiting.push_back((a, b));
            self.release();
            if self.waiting.len() > MAX_WAITING_FOR_INFO {
                return Err(self.missing_info().expect("frames wait for a CameraInfo"));
            }
        }
        Ok(())
    }
}

impl Iterator for BagFrames {
    type Item = Result<BagFrame, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(f) = self.ready.pop_front() {
                return Some(Ok(f));
            }
            if self.ended {
                return None;
            }
            match self.reader.next() {
                None => {
                    self.ended = true;
                    let unpaired = self.pairer.finish();
                    self.note_unpaired(unpaired);
                    if let Some(e) = self.missing_info() {
                        return Some(Err(e));
                    }
                }
                Some(Err(e)) => {
                    self.ended = true;
                    return Some(Err(e));
                }
                Some(Ok(msg)) => {
                    if let Err(e) = self.take(msg) {
                        self.ended = true;
                        return Some(Err(e));
                    }
                }
            }
        }
    }
}

/// Nanoseconds since the epoch as `s.nnnnnnnnn s`.
pub fn display_ns(ns: u64) -> String {
    format!("{}.{:09} s", ns / 1_000_000_000, ns % 1_000_000_000)
}
