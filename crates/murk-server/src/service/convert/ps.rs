//! `PhotometricStereoRequest` → ([`PsCapture`], [`PsParams`]) and [`PsResult`] →
//! `PhotometricStereoResult`.

use super::geometry::{intrinsics_from_proto, intrinsics_to_proto};
use super::image::{image_from_proto, image_to_proto, mono_image_from_proto, ImageLimits};
use crate::service::proto::v1 as pb;
use murk::error::{MurkError, Result};
use murk::image::ImageF32;
use murk::ps::distance::DistanceFit;
use murk::ps::physics::{FacetEmission, FarField, Medium};
use murk::ps::{validate_request, DistanceMode, PointLight, PsCapture, PsMode, PsParams, PsResult};

/// Decodes and fully validates a request (images, lights, medium, every setting and the
/// kernel's memory bound), so nothing invalid is ever queued. Field names are relative to
/// `PhotometricStereoRequest`.
pub fn ps_from_proto(
    req: &pb::PhotometricStereoRequest,
    limits: &ImageLimits,
    max_kernel_bytes: usize,
) -> Result<(PsCapture, PsParams)> {
    if req.lights.len() < 3 {
        return Err(MurkError::invalid(
            "lights",
            format!(
                "photometric stereo needs at least 3 lights, got {}",
                req.lights.len()
            ),
        ));
    }
    if req.lights.len() > murk::ps::capture::MAX_LIGHTS {
        return Err(MurkError::invalid(
            "lights",
            format!(
                "at most {} lights, got {}",
                murk::ps::capture::MAX_LIGHTS,
                req.lights.len()
            ),
        ));
    }
    let mut dims = None;
    let mut images = Vec::with_capacity(req.lights.len());
    let mut backgrounds = Vec::with_capacity(req.lights.len());
    let mut lights = Vec::with_capacity(req.lights.len());
    for (i, l) in req.lights.iter().enumerate() {
        let field = |f: &str| format!("lights[{i}].{f}");
        let load = |img: &Option<pb::Image>, name: &str| -> Result<ImageF32> {
            let img = img
                .as_ref()
                .ok_or_else(|| MurkError::invalid(field(name), "required"))
                .and_then(|im| {
                    mono_image_from_proto(im, limits).map_err(|e| e.within(&field(name)))
                })?;
            Ok(img)
        };
        for (name, list) in [("image", &mut images), ("background", &mut backgrounds)] {
            let img = load(
                if name == "image" {
                    &l.image
                } else {
                    &l.background
                },
                name,
            )?;
            let (w, h) = *dims.get_or_insert(img.dims());
            if img.dims() != (w, h) {
                return Err(MurkError::invalid(
                    field(name),
                    format!(
                        "size {}x{} differs from lights[0].image's {w}x{h}",
                        img.width(),
                        img.height()
                    ),
                ));
            }
            list.push(img);
        }
        let p = l
            .position_mm
            .as_ref()
            .ok_or_else(|| MurkError::invalid(field("position_mm"), "required"))?;
        lights.push(PointLight {
            position_mm: [p.x, p.y, p.z],
            intensity: l.intensity,
        });
    }
    let mask_img = req
        .mask
        .as_ref()
        .ok_or_else(|| MurkError::invalid("mask", "required"))
        .and_then(|i| mono_image_from_proto(i, limits).map_err(|e| e.within("mask")))?;
    mask_img.ensure_channels(1).map_err(|e| e.within("mask"))?;
    mask_img.ensure_finite().map_err(|e| e.within("mask"))?;
    let (w, h) = dims.unwrap_or((0, 0));
    if mask_img.dims() != (w, h) {
        return Err(MurkError::invalid(
            "mask",
            format!(
                "size {}x{} differs from lights[0].image's {w}x{h}",
                mask_img.width(),
                mask_img.height()
            ),
        ));
    }
    let intrinsics = req
        .intrinsics
        .as_ref()
        .map(intrinsics_from_proto)
        .ok_or_else(|| MurkError::invalid("intrinsics", "required"))?;
    let capture = PsCapture {
        mask: mask_img.data().iter().map(|&v| v > 0.5).collect(),
        images,
        backgrounds,
        lights,
        intrinsics,
        medium: Medium {
            beta_per_mm: req.beta_per_mm,
            sigma_per_mm: req.sigma_per_mm,
        },
    };
    let mut params = params_from_proto(req, max_kernel_bytes)?;
    if req.auto_support {
        if req.support_r != 0 {
            return Err(MurkError::invalid(
                "support_r",
                format!("must be 0 (unset) with auto_support, got {}", req.support_r),
            ));
        }
        let choice =
            murk::ps::choose_support(&capture.mask, w, h, params.near_radius_px, max_kernel_bytes)
                .map_err(rename_fields)?;
        params.support_r = choice.support_r;
        if req.far_cell == 0 {
            params.far_cell = choice.far_cell;
        }
    }
    if let Some(img) = &req.initial_depth_mm {
        let d = image_from_proto(img, limits).map_err(|e| e.within("initial_depth_mm"))?;
        d.ensure_channels(1)
            .map_err(|e| e.within("initial_depth_mm"))?;
        if d.dims() != (w, h) {
            return Err(MurkError::invalid(
                "initial_depth_mm",
                format!(
                    "size {}x{} differs from lights[0].image's {w}x{h}",
                    d.width(),
                    d.height()
                ),
            ));
        }
        params.initial_depth_mm = Some(d.into_vec());
    }
    validate_request(&capture, &params).map_err(rename_fields)?;
    Ok((capture, params))
}

/// Library field paths → request field paths where they differ.
fn rename_fields(e: MurkError) -> MurkError {
    let over_limit = matches!(e, MurkError::OverLimit { .. });
    match e {
        MurkError::InvalidArgument { field, reason } | MurkError::OverLimit { field, reason } => {
            let field = if let Some(rest) = field.strip_prefix("medium.") {
                rest.to_string()
            } else if let Some(rest) = field.strip_prefix("images[") {
                let (idx, tail) = rest.split_once(']').unwrap_or((rest, ""));
                format!("lights[{idx}].image{tail}")
            } else if let Some(rest) = field.strip_prefix("backgrounds[") {
                let (idx, tail) = rest.split_once(']').unwrap_or((rest, ""));
                format!("lights[{idx}].background{tail}")
            } else {
                match field.as_str() {
                    "solver.rel_tolerance" => "solver_tolerance".into(),
                    "solver.max_iterations" => "solver_max_iterations".into(),
                    _ => field,
                }
            };
            if over_limit {
                MurkError::OverLimit { field, reason }
            } else {
                MurkError::InvalidArgument { field, reason }
            }
        }
        other => other,
    }
}

fn params_from_proto(
    req: &pb::PhotometricStereoRequest,
    max_kernel_bytes: usize,
) -> Result<PsParams> {
    let d = PsParams::default();
    let mode = match pb::PsMode::try_from(req.mode) {
        Ok(pb::PsMode::Unspecified) | Ok(pb::PsMode::Full) => PsMode::Full,
        Ok(pb::PsMode::BackscatterOnly) => PsMode::BackscatterOnly,
        Err(_) => {
            return Err(MurkError::invalid(
                "mode",
                format!("unknown mode {}", req.mode),
            ))
        }
    };
    let far_field = match pb::PsFarField::try_from(req.far_field) {
        Ok(pb::PsFarField::Unspecified) => d.far_field,
        Ok(pb::PsFarField::PerPixel) => FarField::PerPixel,
        Ok(pb::PsFarField::ConstantEpsilon) => FarField::ConstantEpsilon,
        Ok(pb::PsFarField::Blocks) => FarField::Blocks,
        Err(_) => {
            return Err(MurkError::invalid(
                "far_field",
                format!("unknown far-field model {}", req.far_field),
            ))
        }
    };
    let facet_emission = match pb::PsFacetEmission::try_from(req.facet_emission) {
        Ok(pb::PsFacetEmission::Unspecified) => d.facet_emission,
        Ok(pb::PsFacetEmission::Lambertian) => FacetEmission::Lambertian,
        Ok(pb::PsFacetEmission::Isotropic) => FacetEmission::Isotropic,
        Err(_) => {
            return Err(MurkError::invalid(
                "facet_emission",
                format!("unknown facet emission model {}", req.facet_emission),
            ))
        }
    };
    Ok(PsParams {
        initial_distance_mm: req.initial_distance_mm,
        distance: if req.fix_distance {
            DistanceMode::Fixed
        } else {
            DistanceMode::Estimate
        },
        initial_depth_mm: None,
        support_r: if req.support_r == 0 {
            d.support_r
        } else {
            req.support_r as usize
        },
        far_cell: if req.far_cell == 0 {
            d.far_cell
        } else {
            req.far_cell as usize
        },
        near_radius_px: if req.near_radius_px == 0 {
            d.near_radius_px
        } else {
            req.near_radius_px as usize
        },
        max_iterations: if req.max_iterations == 0 {
            d.max_iterations
        } else {
            req.max_iterations as usize
        },
        tolerance: req.tolerance.unwrap_or(d.tolerance),
        kernel_rebuild_tolerance: req
            .kernel_rebuild_tolerance
            .unwrap_or(d.kernel_rebuild_tolerance),
        mode,
        median_filter: !req.no_median_filter,
        backscatter_tail: !req.no_backscatter_tail,
        shadow_ratio: req.shadow_ratio.unwrap_or(d.shadow_ratio),
        exact_g: !req.linear_g,
        smoothness_s: req.smoothness_s.unwrap_or(d.smoothness_s),
        solver: murk::ps::bicgstab::BicgstabParams {
            rel_tolerance: req.solver_tolerance.unwrap_or(d.solver.rel_tolerance),
            max_iterations: req
                .solver_max_iterations
                .map_or(d.solver.max_iterations, |v| v as usize),
        },
        max_kernel_bytes,
        far_field,
        facet_emission,
    })
}

/// Writes the defaults into unset fields so equivalent requests share a job id.
pub fn canonicalize_ps_request(req: &mut pb::PhotometricStereoRequest) {
    let d = PsParams::default();
    // With auto_support the support (and a zero far cell) follow from the mask, which is part of
    // the request: left as 0 they still identify the job.
    if req.support_r == 0 && !req.auto_support {
        req.support_r = d.support_r as u32;
    }
    if req.max_iterations == 0 {
        req.max_iterations = d.max_iterations as u32;
    }
    if req.far_cell == 0 && !req.auto_support {
        req.far_cell = d.far_cell as u32;
    }
    if req.near_radius_px == 0 {
        req.near_radius_px = d.near_radius_px as u32;
    }
    if req.mode == pb::PsMode::Unspecified as i32 {
        req.mode = pb::PsMode::Full as i32;
    }
    if req.far_field == pb::PsFarField::Unspecified as i32 {
        req.far_field = far_field_to_proto(d.far_field) as i32;
    }
    if req.facet_emission == pb::PsFacetEmission::Unspecified as i32 {
        req.facet_emission = facet_emission_to_proto(d.facet_emission) as i32;
    }
    req.tolerance.get_or_insert(d.tolerance);
    req.kernel_rebuild_tolerance
        .get_or_insert(d.kernel_rebuild_tolerance);
    req.smoothness_s.get_or_insert(d.smoothness_s);
    req.shadow_ratio.get_or_insert(d.shadow_ratio);
    req.solver_tolerance.get_or_insert(d.solver.rel_tolerance);
    req.solver_max_iterations
        .get_or_insert(d.solver.max_iterations as u32);
}

fn far_field_to_proto(f: FarField) -> pb::PsFarField {
    match f {
        FarField::PerPixel => pb::PsFarField::PerPixel,
        FarField::ConstantEpsilon => pb::PsFarField::ConstantEpsilon,
        FarField::Blocks => pb::PsFarField::Blocks,
    }
}

fn facet_emission_to_proto(e: FacetEmission) -> pb::PsFacetEmission {
    match e {
        FacetEmission::Lambertian => pb::PsFacetEmission::Lambertian,
        FacetEmission::Isotropic => pb::PsFacetEmission::Isotropic,
    }
}

/// A request for `capture` (clients: CLI, demo, tests, benchmarks). Images travel as raw f32.
pub fn ps_request_to_proto(capture: &PsCapture, params: &PsParams) -> pb::PhotometricStereoRequest {
    let (w, h) = capture.dims();
    let mask = ImageF32::from_vec(
        w,
        h,
        1,
        capture
            .mask
            .iter()
            .map(|&b| if b { 1.0 } else { 0.0 })
            .collect(),
    )
    .expect("mask has width*height entries");
    pb::PhotometricStereoRequest {
        lights: capture
            .lights
            .iter()
            .zip(capture.images.iter().zip(&capture.backgrounds))
            .map(|(l, (img, bg))| pb::PsLight {
                position_mm: Some(pb::Vector3 {
                    x: l.position_mm[0],
                    y: l.position_mm[1],
                    z: l.position_mm[2],
                }),
                intensity: l.intensity,
                image: Some(image_to_proto(img)),
                background: Some(image_to_proto(bg)),
            })
            .collect(),
        mask: Some(image_to_proto(&mask)),
        intrinsics: Some(intrinsics_to_proto(&capture.intrinsics)),
        beta_per_mm: capture.medium.beta_per_mm,
        sigma_per_mm: capture.medium.sigma_per_mm,
        initial_distance_mm: params.initial_distance_mm,
        fix_distance: params.distance == DistanceMode::Fixed,
        support_r: params.support_r as u32,
        far_cell: params.far_cell as u32,
        near_radius_px: params.near_radius_px as u32,
        auto_support: false,
        max_iterations: params.max_iterations as u32,
        tolerance: Some(params.tolerance),
        kernel_rebuild_tolerance: Some(params.kernel_rebuild_tolerance),
        mode: match params.mode {
            PsMode::Full => pb::PsMode::Full,
            PsMode::BackscatterOnly => pb::PsMode::BackscatterOnly,
        } as i32,
        no_median_filter: !params.median_filter,
        no_backscatter_tail: !params.backscatter_tail,
        smoothness_s: Some(params.smoothness_s),
        shadow_ratio: Some(params.shadow_ratio),
        solver_tolerance: Some(params.solver.rel_tolerance),
        solver_max_iterations: Some(params.solver.max_iterations as u32),
        return_iteration_normals: false,
        linear_g: !params.exact_g,
        far_field: far_field_to_proto(params.far_field) as i32,
        facet_emission: facet_emission_to_proto(params.facet_emission) as i32,
        initial_depth_mm: params.initial_depth_mm.as_ref().map(|d| {
            image_to_proto(
                &ImageF32::from_vec(w, h, 1, d.clone())
                    .expect("initial depth has width*height values"),
            )
        }),
    }
}

/// Encodes the method's output for the wire.
pub fn ps_to_proto(out: &PsResult, with_history: bool) -> pb::PhotometricStereoResult {
    let (w, h) = (out.width, out.height);
    let img = |c: usize, data: Vec<f32>| {
        image_to_proto(&ImageF32::from_vec(w, h, c, data).expect("sizes match the capture"))
    };
    pb::PhotometricStereoResult {
        iteration_normals: if with_history {
            out.normals_history
                .iter()
                .map(|n| img(3, n.iter().flatten().copied().collect()))
                .collect()
        } else {
            Vec::new()
        },
        normals: Some(img(3, out.normals.iter().flatten().copied().collect())),
        albedo: Some(img(1, out.albedo.clone())),
        depth_mm: Some(img(1, out.depth_mm.clone())),
        iterations: out
            .iterations
            .iter()
            .map(|s| pb::PsIteration {
                iteration: s.iteration as u32,
                relative_depth_change: s.relative_depth_change,
                mean_depth_mm: s.mean_depth_mm,
                solver_iterations: s.solver_iterations.iter().map(|&v| v as u32).collect(),
                solver_residual: s.solver_residual,
                epsilon: s.epsilon,
                constant_term: s.constant_term.clone(),
                kernel_bytes: s.kernel_bytes as u64,
                filled_pixels: s.filled_pixels as u32,
                kernel_seconds: s.kernel_s,
                kernel_reused: s.kernel_reused,
                solve_seconds: s.solve_s,
                normals_seconds: s.normals_s,
                integrate_seconds: s.integrate_s,
                backscatter_tail_seconds: s.tail_s,
                distance_fit: s.distance_fit.as_ref().map(distance_fit_to_proto),
            })
            .collect(),
        initial_distance_fit: out.initial_distance_fit.as_ref().map(distance_fit_to_proto),
        backscatter_seconds: out.backscatter_s,
        total_seconds: out.total_s,
        support_r: out.support_r as u32,
        far_cell: out.far_cell as u32,
    }
}

fn distance_fit_to_proto(f: &DistanceFit) -> pb::PsDistanceFit {
    pb::PsDistanceFit {
        mean_depth_mm: f.mean_depth_mm,
        residual: f.objective,
        pixels: f.pixels as u32,
        at_bound: f.at_bound,
    }
}

fn distance_fit_from_proto(f: &pb::PsDistanceFit) -> DistanceFit {
    DistanceFit {
        mean_depth_mm: f.mean_depth_mm,
        objective: f.residual,
        pixels: f.pixels as usize,
        at_bound: f.at_bound,
    }
}

/// The wire result → the library's output type (clients: CLI, demo, tests).
pub fn ps_from_result(r: &pb::PhotometricStereoResult, mask: &[bool]) -> Result<PsResult> {
    let limits = ImageLimits::default();
    let get = |img: &Option<pb::Image>, name: &str| -> Result<ImageF32> {
        img.as_ref()
            .ok_or_else(|| MurkError::invalid(name, "missing in result"))
            .and_then(|i| image_from_proto(i, &limits).map_err(|e| e.within(name)))
    };
    let normals = get(&r.normals, "normals")?;
    let (w, h) = normals.dims();
    Ok(PsResult {
        width: w,
        height: h,
        normals: normals
            .data()
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        albedo: get(&r.albedo, "albedo")?.into_vec(),
        depth_mm: get(&r.depth_mm, "depth_mm")?.into_vec(),
        mask: mask.to_vec(),
        iterations: r
            .iterations
            .iter()
            .map(|s| murk::ps::PsIterationStats {
                iteration: s.iteration as usize,
                relative_depth_change: s.relative_depth_change,
                mean_depth_mm: s.mean_depth_mm,
                solver_iterations: s.solver_iterations.iter().map(|&v| v as usize).collect(),
                solver_residual: s.solver_residual,
                epsilon: s.epsilon,
                constant_term: s.constant_term.clone(),
                kernel_bytes: s.kernel_bytes as usize,
                filled_pixels: s.filled_pixels as usize,
                kernel_s: s.kernel_seconds,
                kernel_reused: s.kernel_reused,
                solve_s: s.solve_seconds,
                normals_s: s.normals_seconds,
                integrate_s: s.integrate_seconds,
                tail_s: s.backscatter_tail_seconds,
                distance_fit: s.distance_fit.as_ref().map(distance_fit_from_proto),
            })
            .collect(),
        normals_history: r
            .iteration_normals
            .iter()
            .enumerate()
            .map(|(k, i)| {
                image_from_proto(i, &limits)
                    .map_err(|e| e.within(&format!("iteration_normals[{k}]")))
                    .map(|img| {
                        img.data()
                            .chunks_exact(3)
                            .map(|c| [c[0], c[1], c[2]])
                            .collect()
                    })
            })
            .collect::<Result<_>>()?,
        backscatter_s: r.backscatter_seconds,
        total_s: r.total_seconds,
        support_r: r.support_r as usize,
        far_cell: r.far_cell as usize,
        initial_distance_fit: r.initial_distance_fit.as_ref().map(distance_fit_from_proto),
    })
}
