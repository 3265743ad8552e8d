//! The sparse SfM depth map of Eq. 3.8: SfM points projected into the reference camera give
//! `z_sfm(u, v)` where the indicator `m(u, v) = 1`.

use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::mvs::colmap::{ColmapModel, Point3D};
use crate::mvs::pose::Pose;
use crate::params::tracks::{Observation, SfmTracks};

/// [`SparseSample::seen_by`] of a point whose visibility in the sources is unknown: it may be
/// used in every source.
pub const SEEN_BY_EVERY_SOURCE: u32 = u32::MAX;

/// One pixel with `m(u, v) = 1`: integer pixel (murk convention, pixel centres at integers)
/// and the z-depth of the SfM point seen there, scene units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SparseSample {
    /// Column, pixels.
    pub x: u32,
    /// Row, pixels.
    pub y: u32,
    /// Column of the point's projection, pixels, before rounding to `x`: the intensity fits
    /// sample the point where SfM found it, not at its pixel's centre.
    pub u: f32,
    /// Row of the point's projection, pixels, before rounding to `y`.
    pub v: f32,
    /// z-depth in the reference camera, scene units (> 0).
    pub z: f32,
    /// Bit `i` set when source `i` sees the point: its SfM track includes that image, so it is
    /// not occluded there. [`SEEN_BY_EVERY_SOURCE`] when unknown.
    pub seen_by: u32,
}

/// `z_sfm` and `m` of Eq. 3.8 for one reference view, stored as the list of pixels with
/// `m = 1` (a few hundred to a few thousand, against ~50 k pixels), sorted by row then column.
#[derive(Clone, Debug, PartialEq)]
pub struct SparseDepth {
    width: usize,
    height: usize,
    samples: Vec<SparseSample>,
}

/// Which points of a COLMAP model are projected into the reference view.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PointSelection {
    /// Points whose track includes the reference image (SfM matched them there, so they are
    /// visible in it), or every point when the model stores no observations for the reference.
    ObservedInReference,
    /// Every point in front of the camera and inside the image (occluded points included).
    All,
}

/// The world points (scene units) of `model` that `selection` picks for the image named
/// `reference` (see [`PointSelection`]). Fails naming `reference` for an unknown image.
pub fn selected_points(
    model: &ColmapModel,
    reference: &str,
    selection: PointSelection,
) -> Result<Vec<[f64; 3]>> {
    Ok(selected(model, reference, selection)?
        .into_iter()
        .map(|p| p.xyz)
        .collect())
}

/// The points [`selected_points`] picks, with each point's [`SparseSample::seen_by`] mask over
/// `sources` (image names; bit `i` for `sources[i]`, at most 32: the images in its SfM track)
/// and its observations in the reference (view 0) and `sources` (view `1 + i`), in murk's pixel
/// convention (COLMAP's coordinates shifted by −0.5). Masks and observations are empty when the
/// model stores no tracks (every point then counts as seen everywhere). Fails naming
/// `reference` or `sources[i]` for an unknown image. Public as [`SfmTracks::from_colmap`].
pub(crate) fn selected_tracks(
    model: &ColmapModel,
    reference: &str,
    selection: PointSelection,
    sources: &[&str],
) -> Result<SfmTracks> {
    let mut ids = Vec::with_capacity(sources.len());
    for (i, name) in sources.iter().enumerate() {
        let image = model.image_by_name(name).ok_or_else(|| {
            MurkError::invalid(
                format!("sources[{i}]"),
                format!("no image named {name:?} in the model"),
            )
        })?;
        ids.push(image.id);
    }
    if ids.len() > 32 {
        return Err(MurkError::invalid(
            "sources",
            format!("at most 32 sources carry track masks, got {}", ids.len()),
        ));
    }
    let points = selected(model, reference, selection)?;
    let xyz = points.iter().map(|p| p.xyz).collect();
    if model.points.values().all(|p| p.track.is_empty()) {
        return Ok(SfmTracks {
            points: xyz,
            ..SfmTracks::default()
        });
    }
    let masks = points
        .iter()
        .map(|p| {
            ids.iter()
                .enumerate()
                .filter(|(_, id)| p.track.iter().any(|t| t.image_id == **id))
                .fold(0u32, |m, (i, _)| m | (1 << i))
        })
        .collect();
    // `selected` found the reference by name already.
    let reference_id = model.image_by_name(reference).map_or(u32::MAX, |im| im.id);
    let view_of = |image_id: u32| {
        if image_id == reference_id {
            Some(0)
        } else {
            ids.iter()
                .position(|&id| id == image_id)
                .map(|i| i as u32 + 1)
        }
    };
    let mut observations = Vec::new();
    for (i, p) in points.iter().enumerate() {
        for t in &p.track {
            let (Some(view), Some(image)) = (view_of(t.image_id), model.images.get(&t.image_id))
            else {
                continue;
            };
            if let Some(kp) = image.points2d.get(t.point2d_idx as usize) {
                observations.push(Observation {
                    point: i as u32,
                    view,
                    pixel: [kp.xy[0] - 0.5, kp.xy[1] - 0.5],
                });
            }
        }
    }
    Ok(SfmTracks {
        points: xyz,
        seen_by: masks,
        observations,
    })
}

fn selected<'m>(
    model: &'m ColmapModel,
    reference: &str,
    selection: PointSelection,
) -> Result<Vec<&'m Point3D>> {
    let image = model.image_by_name(reference).ok_or_else(|| {
        MurkError::invalid(
            "reference",
            format!("no image named {reference:?} in the model"),
        )
    })?;
    let observed = selection == PointSelection::ObservedInReference
        && image.points2d.iter().any(|p| p.point3d_id.is_some());
    Ok(if observed {
        image
            .points2d
            .iter()
            .filter_map(|p| p.point3d_id)
            .filter_map(|id| model.points.get(&id))
            .collect()
    } else {
        model.points.values().collect()
    })
}

impl SparseDepth {
    /// Projects world points (scene units) with the reference camera; points behind the camera
    /// or outside the `width × height` image are dropped, and where several points fall on one
    /// pixel the nearest is kept (it occludes the others). Non-finite points fail naming
    /// `points[i]`. Every point counts as seen by every source.
    pub fn from_points(
        points: &[[f64; 3]],
        intrinsics: &Intrinsics,
        pose: &Pose,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        Self::from_tracked_points(points, &[], intrinsics, pose, width, height)
    }

    /// [`Self::from_points`] with each point's sources: `seen_by[i]` is point `i`'s
    /// [`SparseSample::seen_by`] mask, or `seen_by` is empty when no track is known. A length
    /// other than 0 or `points.len()` fails naming `seen_by`.
    pub fn from_tracked_points(
        points: &[[f64; 3]],
        seen_by: &[u32],
        intrinsics: &Intrinsics,
        pose: &Pose,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        if !seen_by.is_empty() && seen_by.len() != points.len() {
            return Err(MurkError::invalid(
                "seen_by",
                format!(
                    "one source mask per point or none: {} masks for {} points",
                    seen_by.len(),
                    points.len()
                ),
            ));
        }
        let mut samples: Vec<SparseSample> = Vec::with_capacity(points.len());
        for (i, p) in points.iter().enumerate() {
            if !p.iter().all(|c| c.is_finite()) {
                return Err(MurkError::invalid(
                    format!("points[{i}]"),
                    format!("coordinates must be finite, got {p:?}"),
                ));
            }
            let q = pose.transform(*p);
            let Some((u, v)) = intrinsics.project(q) else {
                continue;
            };
            let (x, y) = (u.round(), v.round());
            if !(x >= 0.0 && y >= 0.0 && x < width as f64 && y < height as f64) {
                continue;
            }
            samples.push(SparseSample {
                x: x as u32,
                y: y as u32,
                u: u as f32,
                v: v as f32,
                z: q[2] as f32,
                seen_by: seen_by.get(i).copied().unwrap_or(SEEN_BY_EVERY_SOURCE),
            });
        }
        samples.sort_by(|a, b| (a.y, a.x, a.z).partial_cmp(&(b.y, b.x, b.z)).unwrap());
        samples.dedup_by(|later, first| later.x == first.x && later.y == first.y);
        Ok(Self {
            width,
            height,
            samples,
        })
    }

    /// Eq. 3.8 from a COLMAP sparse model: the points chosen by `selection` projected into the
    /// image named `reference` (its pose and camera from the model; `width × height` is the
    /// size of the image the depth will be computed for, which must match the camera's).
    /// Fails naming `reference` for an unknown image.
    pub fn from_colmap(
        model: &ColmapModel,
        reference: &str,
        width: usize,
        height: usize,
        selection: PointSelection,
    ) -> Result<Self> {
        let image = model.image_by_name(reference).ok_or_else(|| {
            MurkError::invalid(
                "reference",
                format!("no image named {reference:?} in the model"),
            )
        })?;
        let intrinsics = model.intrinsics_of(image)?;
        let points = selected_points(model, reference, selection)?;
        Self::from_points(&points, &intrinsics, &image.pose, width, height)
    }

    /// From pixels already sorted by row then column with one sample per pixel, all inside.
    pub(crate) fn from_samples(width: usize, height: usize, samples: Vec<SparseSample>) -> Self {
        Self {
            width,
            height,
            samples,
        }
    }

    /// Image width, pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height, pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The pixels with `m = 1`, sorted by row then column, one sample per pixel.
    pub fn samples(&self) -> &[SparseSample] {
        &self.samples
    }

    /// Number of pixels with `m = 1`.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// True when no point is seen.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The `[min, max]` z-depth of the samples (scene units), `None` when empty.
    pub fn depth_range(&self) -> Option<(f32, f32)> {
        let mut it = self.samples.iter().map(|s| s.z);
        let first = it.next()?;
        Some(it.fold((first, first), |(lo, hi), z| (lo.min(z), hi.max(z))))
    }

    /// A quantile of the samples' z-depth (`q ∈ [0, 1]`), `None` when empty.
    pub fn depth_quantile(&self, q: f64) -> Option<f32> {
        if self.samples.is_empty() {
            return None;
        }
        let mut z: Vec<f32> = self.samples.iter().map(|s| s.z).collect();
        let k = ((z.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
        let (_, v, _) = z.select_nth_unstable_by(k, f32::total_cmp);
        Some(*v)
    }

    /// `z_sfm` as an image: the depth where `m = 1`, 0 elsewhere (one channel).
    pub fn to_image(&self) -> ImageF32 {
        let mut img = ImageF32::filled(self.width, self.height, 1, 0.0);
        for s in &self.samples {
            img.set(s.x as usize, s.y as usize, 0, s.z);
        }
        img
    }
}

impl SfmTracks {
    /// The points that `selection` picks for the image named `reference` of `model`, their
    /// source masks over `sources` (image names) and their observations in the reference and
    /// the sources. COLMAP's pixel coordinates (top-left pixel centre at (0.5, 0.5)) are
    /// shifted into murk's. Fails naming `reference` or `sources[i]` for an unknown image.
    pub fn from_colmap(
        model: &ColmapModel,
        reference: &str,
        selection: PointSelection,
        sources: &[&str],
    ) -> Result<Self> {
        selected_tracks(model, reference, selection, sources)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mvs::colmap::{ColmapCamera, ColmapImage, Point2D, Point3D, TrackElement};
    use std::collections::BTreeMap;

    fn camera() -> Intrinsics {
        Intrinsics::new(50.0, 50.0, 15.5, 11.5)
    }

    #[test]
    fn projects_keeps_nearest_and_drops_outside() {
        let k = camera();
        let pose = Pose::identity();
        let pts = [
            [0.0, 0.0, 2.0],  // centre pixel (15.5 → 16, 11.5 → 12)
            [0.0, 0.0, 3.0],  // same pixel, farther: dropped
            [0.0, 0.0, -1.0], // behind
            [10.0, 0.0, 1.0], // outside
            [0.2, 0.1, 2.0],  // (20.5 → 21, 14)
        ];
        let s = SparseDepth::from_points(&pts, &k, &pose, 32, 24).unwrap();
        assert_eq!(s.len(), 2);
        assert_eq!(
            s.samples()[0],
            SparseSample {
                x: 16,
                y: 12,
                u: 15.5,
                v: 11.5,
                z: 2.0,
                seen_by: SEEN_BY_EVERY_SOURCE,
            }
        );
        assert_eq!((s.samples()[1].x, s.samples()[1].y), (21, 14));
        assert_eq!(s.depth_range(), Some((2.0, 2.0)));
        let img = s.to_image();
        assert_eq!(img.get(16, 12, 0), 2.0);
        assert_eq!(img.get(0, 0, 0), 0.0);
        let err = SparseDepth::from_points(&[[f64::NAN, 0.0, 1.0]], &k, &pose, 32, 24);
        assert_eq!(err.unwrap_err().field(), Some("points[0]"));
    }

    #[test]
    fn colmap_selection_uses_the_reference_track() {
        let k = camera();
        let cam = ColmapCamera::from_intrinsics(1, &k, 32, 24).unwrap();
        let seen = Point3D {
            id: 1,
            xyz: [0.0, 0.0, 2.0],
            rgb: [0; 3],
            error: 0.0,
            track: vec![TrackElement {
                image_id: 1,
                point2d_idx: 0,
            }],
        };
        let unseen = Point3D {
            id: 2,
            xyz: [0.1, 0.0, 4.0],
            track: vec![],
            ..seen.clone()
        };
        let image = ColmapImage::new(
            1,
            1,
            "ref.png",
            &Pose::identity(),
            vec![Point2D {
                xy: [16.0, 12.0],
                point3d_id: Some(1),
            }],
        )
        .unwrap();
        let model = ColmapModel {
            cameras: BTreeMap::from([(1, cam)]),
            images: BTreeMap::from([(1, image)]),
            points: BTreeMap::from([(1, seen), (2, unseen)]),
        };
        let obs = SparseDepth::from_colmap(
            &model,
            "ref.png",
            32,
            24,
            PointSelection::ObservedInReference,
        )
        .unwrap();
        assert_eq!(obs.len(), 1);
        let all = SparseDepth::from_colmap(&model, "ref.png", 32, 24, PointSelection::All).unwrap();
        assert_eq!(all.len(), 2);
        let err = SparseDepth::from_colmap(&model, "x.png", 32, 24, PointSelection::All);
        assert_eq!(err.unwrap_err().field(), Some("reference"));
    }

    #[test]
    fn track_masks_name_the_sources_that_saw_each_point() {
        let k = camera();
        let cam = ColmapCamera::from_intrinsics(1, &k, 32, 24).unwrap();
        let obs = |image_id| TrackElement {
            image_id,
            point2d_idx: 0,
        };
        let point = |id, x, track| Point3D {
            id,
            xyz: [x, 0.0, 2.0],
            rgb: [0; 3],
            error: 0.0,
            track,
        };
        let image = |id, name: &str| {
            ColmapImage::new(
                id,
                1,
                name,
                &Pose::identity(),
                vec![Point2D {
                    xy: [16.0, 12.0],
                    point3d_id: None,
                }],
            )
            .unwrap()
        };
        let model = ColmapModel {
            cameras: BTreeMap::from([(1, cam)]),
            images: BTreeMap::from([
                (1, image(1, "ref.png")),
                (2, image(2, "a.png")),
                (3, image(3, "b.png")),
            ]),
            points: BTreeMap::from([
                (1, point(1, 0.0, vec![obs(1), obs(2), obs(3)])),
                (2, point(2, 0.1, vec![obs(1), obs(3)])), // hidden from a.png
                (3, point(3, 0.2, vec![obs(1)])),
            ]),
        };
        // Bit i for sources[i], whatever the image ids.
        let SfmTracks {
            points: xyz,
            seen_by: masks,
            ..
        } = selected_tracks(&model, "ref.png", PointSelection::All, &["b.png", "a.png"]).unwrap();
        assert_eq!(xyz.len(), 3);
        assert_eq!(masks, vec![0b11, 0b01, 0b00]);
        let sparse =
            SparseDepth::from_tracked_points(&xyz, &masks, &k, &Pose::identity(), 32, 24).unwrap();
        let seen: Vec<u32> = sparse.samples().iter().map(|s| s.seen_by).collect();
        assert_eq!(seen, vec![0b11, 0b01, 0b00]);
        // The masks survive the search's downsampling with their points.
        let coarse = sparse.downsampled(2);
        assert!(coarse.samples().iter().all(|s| masks.contains(&s.seen_by)));
        // A model without tracks gives no masks: every point counts as seen everywhere.
        let mut untracked = model.clone();
        for p in untracked.points.values_mut() {
            p.track.clear();
        }
        let none = selected_tracks(&untracked, "ref.png", PointSelection::All, &["a.png"]).unwrap();
        assert!(none.seen_by.is_empty() && none.observations.is_empty());
        let e = selected_tracks(&model, "ref.png", PointSelection::All, &["c.png"]);
        assert_eq!(e.unwrap_err().field(), Some("sources[0]"));
        let e = SparseDepth::from_tracked_points(&xyz, &[1], &k, &Pose::identity(), 32, 24);
        assert_eq!(e.unwrap_err().field(), Some("seen_by"));
    }
}
