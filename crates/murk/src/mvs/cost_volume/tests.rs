use super::*;
use crate::atmosphere::haze;

const W: usize = 64;
const H: usize = 48;
const TEX_SCALE: f64 = 0.5;

fn k() -> Intrinsics {
    Intrinsics::new(120.0, 120.0, 31.5, 23.5)
}

/// Smooth, aperiodic-looking RGB texture on the plane, values in [0.05, 0.95].
fn texture(x: f64, y: f64, c: usize) -> f32 {
    let cf = c as f64;
    let (x, y) = (x * TEX_SCALE, y * TEX_SCALE);
    let a = (x * (31.0 + 7.0 * cf) + y * (11.0 - 5.0 * cf) + cf).sin();
    let b = (x * (-13.0 + 3.0 * cf) + y * (29.0 + 4.0 * cf) + 2.0 * cf).sin();
    let d = (x * 17.0 * (1.0 + 0.3 * cf) - y * 19.0 + 0.5).sin() * (y * 7.0 + x * 3.0).cos();
    (0.5 + 0.45 * (a + b + d) / 3.0) as f32
}

/// Source pose (world = reference camera frame) with centre `c` and a small yaw.
fn source_pose(c: [f64; 3], yaw: f64) -> Pose {
    let r = Pose::from_colmap([(yaw / 2.0).cos(), 0.0, (yaw / 2.0).sin(), 0.0], [0.0; 3]).unwrap();
    Pose::new(*r.rotation(), -r.rotate(c)).unwrap()
}

/// Renders the textured plane `z = depth` (reference frame) from a camera with `pose`:
/// returns the clear image and its z-depth map.
fn render(pose: &Pose, depth: f64) -> (ImageF32, ImageF32) {
    let kk = k();
    let inv = pose.inverse();
    let centre = pose.camera_center();
    let mut img = ImageF32::filled(W, H, 3, 0.0);
    let mut z = ImageF32::filled(W, H, 1, 0.0);
    for v in 0..H {
        for u in 0..W {
            let ray = kk.ray(u as f64, v as f64);
            let d_cam = [ray[0] / ray[2], ray[1] / ray[2], 1.0];
            let d_world = inv.rotate(d_cam);
            let lambda = (depth - centre[2]) / d_world[2];
            let x = centre[0] + lambda * d_world[0];
            let y = centre[1] + lambda * d_world[1];
            for c in 0..3 {
                img.set(u, v, c, texture(x, y, c));
            }
            // d_cam has unit z, so λ is the z-depth in this camera.
            z.set(u, v, 0, lambda as f32);
        }
    }
    (img, z)
}

struct Scene {
    images: Vec<ImageF32>,
    poses: Vec<Pose>,
}

/// Reference plus sources looking at the plane `z = depth`, hazed with `(a, beta)`.
fn scene(depth: f64, a: f32, beta: f32, centres: &[[f64; 3]]) -> Scene {
    let mut poses = vec![Pose::identity()];
    poses.extend(
        centres
            .iter()
            .enumerate()
            .map(|(k, c)| source_pose(*c, 0.02 * (k as f64 + 1.0))),
    );
    let images = poses
        .iter()
        .map(|p| {
            let (j, z) = render(p, depth);
            haze(&j, &z, a, beta).unwrap()
        })
        .collect();
    Scene { images, poses }
}

impl Scene {
    fn views(&self) -> Vec<View<'_>> {
        self.images
            .iter()
            .zip(&self.poses)
            .map(|(image, pose)| View {
                image,
                intrinsics: k(),
                pose: *pose,
            })
            .collect()
    }
}

fn planes() -> PlaneSet {
    // Disparity spans 36 px (z = 1) … 3.6 px (z = 10) for a 0.3 baseline: ~0.5 px per plane.
    PlaneSet::new(1.0, 10.0, 64).unwrap()
}

fn build(s: &Scene, kind: CostKind) -> CostVolume {
    let v = s.views();
    build_cost_volume(&v[0], &v[1..], &planes(), kind, &Monitor::noop()).unwrap()
}

use crate::error::field_of;

#[test]
fn beta_zero_makes_both_volumes_identical() {
    let s = scene(2.3, 0.8, 0.4, &[[0.3, 0.02, 0.05], [-0.25, -0.03, 0.0]]);
    let ordinary = build(&s, CostKind::Ordinary);
    let dehazing = build(
        &s,
        CostKind::Dehazing(AtmosphereParams {
            airlight: 0.8,
            beta: 0.0,
        }),
    );
    assert_eq!(ordinary.data(), dehazing.data());
    // And the volume is not trivially constant.
    let (lo, hi) = ordinary
        .data()
        .iter()
        .fold((f32::MAX, f32::MIN), |(l, h), &c| (l.min(c), h.max(c)));
    assert!(lo < 0.05 && hi > 0.5, "{lo} .. {hi}");
}

/// Share of pixels, among those whose true match lies inside every source, whose per-pixel
/// argmin is within one plane of the true depth.
fn recovered_share(s: &Scene, vol: &CostVolume, depth: f64) -> f64 {
    let p = vol.planes();
    let truth = p.index_of_inverse_depth(1.0 / depth);
    let warps: Vec<PlaneWarp> = s.poses[1..]
        .iter()
        .map(|pose| PlaneWarp::new(&k(), &k(), &Pose::relative(&s.poses[0], pose), depth))
        .collect();
    let best = vol.argmin_planes();
    let (mut ok, mut n) = (0usize, 0usize);
    for y in 0..H {
        for x in 0..W {
            let seen = warps.iter().all(|w| {
                let (u, v, _) = w.map(x as f64, y as f64);
                u >= 1.0 && v >= 1.0 && u <= (W - 2) as f64 && v <= (H - 2) as f64
            });
            if seen {
                n += 1;
                ok += usize::from((best[y * W + x] as f64 - truth).abs() <= 1.0 + 1e-9);
            }
        }
    }
    assert!(n > W * H / 4, "too few observed pixels: {n}");
    ok as f64 / n as f64
}

#[test]
fn fronto_parallel_plane_is_recovered() {
    // On plane 28 (z ≈ 2.0); in haze the transmission is e^{−0.5·2} ≈ 0.37.
    let depth = planes().depth(28.0);
    let atm = AtmosphereParams {
        airlight: 0.85,
        beta: 0.5,
    };
    for centres in [
        vec![[0.3, 0.02, 0.05]],
        vec![[0.3, 0.02, 0.05], [-0.25, -0.03, 0.0]],
    ] {
        let n = centres.len();
        let clear = scene(depth, atm.airlight, 0.0, &centres);
        let share = recovered_share(&clear, &build(&clear, CostKind::Ordinary), depth);
        assert!(share >= 0.99, "ordinary, clear, {n} source(s): {share}");

        // In haze the two views see the same surface point at different depths (ζ ≠ z), so
        // its hazy intensities differ by (J − A)(t_s − t_r) and the ordinary volume's minimum
        // drifts; the dehazing volume models exactly that (Eq. 3.6).
        let hazy = scene(depth, atm.airlight, atm.beta, &centres);
        let dcv = recovered_share(&hazy, &build(&hazy, CostKind::Dehazing(atm)), depth);
        let ocv = recovered_share(&hazy, &build(&hazy, CostKind::Ordinary), depth);
        assert!(dcv >= 0.99, "dehazing, hazy, {n} source(s): {dcv}");
        assert!(
            dcv >= ocv,
            "hazy, {n} source(s): dehazing {dcv} < ordinary {ocv}"
        );
    }
}

/// The dehazing volume at a few voxels, recomputed the long way: back-project, transform,
/// project, bilinear by hand, `J = (I − A)/t + A` with `t` from ζ (Eq. 3.5–3.7).
#[test]
fn dehazing_voxels_match_direct_evaluation() {
    let atm = AtmosphereParams {
        airlight: 0.9,
        beta: 0.3,
    };
    let s = scene(3.0, atm.airlight, atm.beta, &[[0.3, 0.02, 0.05]]);
    let vol = build(&s, CostKind::Dehazing(atm));
    let rel = Pose::relative(&s.poses[0], &s.poses[1]);
    let (ir, is) = (&s.images[0], &s.images[1]);
    let mut checked = 0;
    for &(x, y) in &[(10usize, 10usize), (40, 20), (50, 40), (5, 30), (33, 7)] {
        for i in (0..64).step_by(3) {
            let z = vol.planes().depth(i as f64);
            let ray = k().ray(x as f64, y as f64);
            let q = rel.transform([ray[0] / ray[2] * z, ray[1] / ray[2] * z, z]);
            let Some((u, v)) = k().project(q) else {
                continue;
            };
            if !(u >= 0.0 && v >= 0.0 && u <= (W - 1) as f64 && v <= (H - 1) as f64) {
                assert_eq!(vol.cost(x, y, i), 3.0);
                continue;
            }
            let (x0, y0) = (u.floor() as usize, v.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(W - 1), (y0 + 1).min(H - 1));
            let (fx, fy) = (u - x0 as f64, v - y0 as f64);
            let (a, b) = (atm.airlight as f64, atm.beta as f64);
            let (tr, ts) = ((-b * z).exp(), (-b * q[2]).exp());
            let mut cost = 0.0;
            let mut inside = true;
            for c in 0..3 {
                let g = |xx: usize, yy: usize| is.get(xx, yy, c) as f64;
                let sample = (1.0 - fy) * ((1.0 - fx) * g(x0, y0) + fx * g(x1, y0))
                    + fy * ((1.0 - fx) * g(x0, y1) + fx * g(x1, y1));
                let jr = (ir.get(x, y, c) as f64 - a) / tr + a;
                let js = (sample - a) / ts + a;
                inside &= (0.0..=1.0).contains(&jr) && (0.0..=1.0).contains(&js);
                cost += (jr - js).abs();
            }
            let got = vol.cost(x, y, i) as f64;
            if inside {
                assert!(
                    (got - cost).abs() < 1e-3,
                    "({x}, {y}, {i}): {got} vs {cost}"
                );
                checked += 1;
            } else {
                // Values within rounding of the [0, 1] boundary may fall either way.
                assert!(
                    got == 3.0 || (got - cost).abs() < 1e-3,
                    "({x}, {y}, {i}): {got}"
                );
            }
        }
    }
    assert!(checked > 10, "only {checked} voxels checked");
}

#[test]
fn unobserved_voxels_get_the_penalty_and_gray_works() {
    let gray = ImageF32::from_fn(W, H, |x, y| texture(x as f64 * 0.01, y as f64 * 0.01, 0));
    let behind = Pose::from_colmap([0.0, 0.0, 1.0, 0.0], [0.0; 3]).unwrap(); // 180° about y
    let r = View {
        image: &gray,
        intrinsics: k(),
        pose: Pose::identity(),
    };
    let s = View { pose: behind, ..r };
    let vol = build_cost_volume(&r, &[s], &planes(), CostKind::Ordinary, &Monitor::noop()).unwrap();
    assert_eq!(vol.penalty(), 1.0);
    assert!(vol.data().iter().all(|&c| c == 1.0));
    // Same view as its own source: zero cost everywhere (identity warp, every plane).
    let vol = build_cost_volume(&r, &[r], &planes(), CostKind::Ordinary, &Monitor::noop()).unwrap();
    assert!(vol.data().iter().all(|&c| c == 0.0));
}

#[test]
fn bad_inputs_name_fields() {
    let s = scene(2.0, 0.8, 0.3, &[[0.3, 0.0, 0.0]]);
    let v = s.views();
    let run = |r: &View<'_>, src: &[View<'_>], p: &PlaneSet, kind: CostKind| {
        field_of(build_cost_volume(r, src, p, kind, &Monitor::noop()).unwrap_err())
    };
    let p = planes();
    assert_eq!(run(&v[0], &[], &p, CostKind::Ordinary), "sources");
    let small = ImageF32::filled(W - 1, H, 3, 0.5);
    let bad_src = View {
        image: &small,
        ..v[1]
    };
    assert_eq!(
        run(&v[0], &[bad_src], &p, CostKind::Ordinary),
        "sources[0].image"
    );
    let four = ImageF32::filled(W, H, 4, 0.5);
    let bad_ref = View {
        image: &four,
        ..v[0]
    };
    assert_eq!(
        run(&bad_ref, &v[1..], &p, CostKind::Ordinary),
        "reference.image"
    );
    let bad_k = View {
        intrinsics: Intrinsics::new(0.0, 1.0, 0.0, 0.0),
        ..v[0]
    };
    assert_eq!(
        run(&bad_k, &v[1..], &p, CostKind::Ordinary),
        "reference.intrinsics.fx"
    );
    let flat = PlaneSet {
        near: 2.0,
        far: 2.0,
        num_planes: 8,
    };
    assert_eq!(run(&v[0], &v[1..], &flat, CostKind::Ordinary), "planes.far");
    let none = PlaneSet { num_planes: 0, ..p };
    assert_eq!(
        run(&v[0], &v[1..], &none, CostKind::Ordinary),
        "planes.num_planes"
    );
    let dark = CostKind::Dehazing(AtmosphereParams {
        airlight: 0.0,
        beta: 0.1,
    });
    assert_eq!(run(&v[0], &v[1..], &p, dark), "atmosphere.airlight");
    let neg = CostKind::Dehazing(AtmosphereParams {
        airlight: 0.8,
        beta: -0.1,
    });
    assert_eq!(run(&v[0], &v[1..], &p, neg), "atmosphere.beta");
}

#[test]
fn cancellation_stops_the_sweep() {
    let s = scene(2.0, 0.8, 0.3, &[[0.3, 0.0, 0.0]]);
    let v = s.views();
    let m = Monitor::noop();
    m.cancel();
    assert_eq!(
        build_cost_volume(&v[0], &v[1..], &planes(), CostKind::Ordinary, &m),
        Err(MurkError::Cancelled)
    );
}

/// Every residual space × range penalty, with an explicit noise level.
fn all_options() -> Vec<DehazingOptions> {
    let mut out = Vec::new();
    for residual in [
        DehazingResidual::Eq37,
        DehazingResidual::ObservationSpace,
        DehazingResidual::NoiseWhitened,
    ] {
        for range in [
            RangePenalty::Hard,
            RangePenalty::NoiseAware { k: 3.0 },
            RangePenalty::ReferenceAware { k: 3.0 },
            RangePenalty::Soft { k: 3.0 },
            RangePenalty::Off,
        ] {
            for noise_sigma in [None, Some(0.02)] {
                out.push(DehazingOptions {
                    residual,
                    range,
                    noise_sigma,
                });
            }
        }
    }
    out
}

#[test]
fn beta_zero_makes_every_dehazing_mode_ordinary() {
    let s = scene(2.3, 0.8, 0.4, &[[0.3, 0.02, 0.05], [-0.25, -0.03, 0.0]]);
    let ordinary = build(&s, CostKind::Ordinary);
    let atm = AtmosphereParams {
        airlight: 0.8,
        beta: 0.0,
    };
    for o in all_options() {
        let d = build(&s, CostKind::DehazingWith(atm, o));
        assert!(ordinary.data() == d.data(), "{o:?}");
    }
    assert_eq!(
        build(&s, CostKind::Dehazing(atm)).data(),
        build(&s, CostKind::DehazingWith(atm, DehazingOptions::EQ37)).data()
    );
}

/// The observation-space and whitened residuals at a few voxels, recomputed the long way:
/// `Σ_c |(I_r − A) − (t_r/t_s)(I_s − A)|`, times `sqrt(2/(1 + (t_r/t_s)²))` when whitened.
#[test]
fn observation_space_voxels_match_direct_evaluation() {
    let atm = AtmosphereParams {
        airlight: 0.9,
        beta: 0.3,
    };
    let s = scene(3.0, atm.airlight, atm.beta, &[[0.3, 0.02, 0.05]]);
    let opts = |residual| DehazingOptions {
        residual,
        range: RangePenalty::Off,
        noise_sigma: None,
    };
    let obs = build(
        &s,
        CostKind::DehazingWith(atm, opts(DehazingResidual::ObservationSpace)),
    );
    let white = build(
        &s,
        CostKind::DehazingWith(atm, opts(DehazingResidual::NoiseWhitened)),
    );
    let rel = Pose::relative(&s.poses[0], &s.poses[1]);
    let (ir, is) = (&s.images[0], &s.images[1]);
    let mut checked = 0;
    for &(x, y) in &[(10usize, 10usize), (40, 20), (50, 40), (5, 30), (33, 7)] {
        for i in (0..64).step_by(3) {
            let z = obs.planes().depth(i as f64);
            let ray = k().ray(x as f64, y as f64);
            let q = rel.transform([ray[0] / ray[2] * z, ray[1] / ray[2] * z, z]);
            let Some((u, v)) = k().project(q) else {
                continue;
            };
            if !(u >= 0.0 && v >= 0.0 && u <= (W - 1) as f64 && v <= (H - 1) as f64) {
                assert_eq!(obs.cost(x, y, i), 3.0);
                continue;
            }
            let (x0, y0) = (u.floor() as usize, v.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(W - 1), (y0 + 1).min(H - 1));
            let (fx, fy) = (u - x0 as f64, v - y0 as f64);
            let (a, b) = (atm.airlight as f64, atm.beta as f64);
            let (tr, ts) = ((-b * z).exp(), (-b * q[2]).exp());
            let mut cost = 0.0;
            for c in 0..3 {
                let g = |xx: usize, yy: usize| is.get(xx, yy, c) as f64;
                let sample = (1.0 - fy) * ((1.0 - fx) * g(x0, y0) + fx * g(x1, y0))
                    + fy * ((1.0 - fx) * g(x0, y1) + fx * g(x1, y1));
                cost += ((ir.get(x, y, c) as f64 - a) - tr / ts * (sample - a)).abs();
            }
            let got = obs.cost(x, y, i) as f64;
            assert!(
                (got - cost).abs() < 1e-4,
                "({x}, {y}, {i}): {got} vs {cost}"
            );
            let r = tr / ts;
            let want = cost * (2.0 / (1.0 + r * r)).sqrt();
            let got = white.cost(x, y, i) as f64;
            assert!(
                (got - want).abs() < 1e-4,
                "({x}, {y}, {i}): {got} vs {want}"
            );
            checked += 1;
        }
    }
    assert!(checked > 10, "only {checked} voxels checked");
}

/// Consistency of the range penalties: a zero noise margin is Eq. 3.7's hard check, a huge
/// one is no check; the soft penalty only adds cost and stays within `γ`.
#[test]
fn range_penalties_are_consistent() {
    let atm = AtmosphereParams {
        airlight: 0.85,
        beta: 0.5,
    };
    let s = scene(2.0, atm.airlight, atm.beta, &[[0.3, 0.02, 0.05]]);
    let with = |range, sigma| {
        build(
            &s,
            CostKind::DehazingWith(
                atm,
                DehazingOptions {
                    residual: DehazingResidual::Eq37,
                    range,
                    noise_sigma: Some(sigma),
                },
            ),
        )
    };
    let hard = build(&s, CostKind::Dehazing(atm));
    let off = with(RangePenalty::Off, 0.0);
    assert!(hard.data() != off.data(), "the hard check never fired");
    assert!(with(RangePenalty::NoiseAware { k: 3.0 }, 0.0).data() == hard.data());
    assert!(off.data().iter().all(|&c| (0.0..=3.0).contains(&c)));
    assert!(with(RangePenalty::NoiseAware { k: 1e30 }, 1.0).data() == off.data());
    assert!(with(RangePenalty::Soft { k: 1e30 }, 1.0).data() == off.data());
    let soft = with(RangePenalty::Soft { k: 0.0 }, 0.0);
    for ((&s, &o), &h) in soft.data().iter().zip(off.data()).zip(hard.data()) {
        assert!(s >= o && s <= 3.0, "{s} vs off {o}");
        // Where the hard check passes there is no excursion.
        if h < 3.0 {
            assert!((s - o).abs() <= 1e-6 * o.max(1.0), "{s} vs {o}");
        }
    }
}

#[test]
fn noise_sigma_is_estimated_robustly() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    for sigma in [0.0f32, 0.005, 0.02] {
        let img = ImageF32::from_fn(128, 96, |x, y| {
            let v = texture(x as f64 * 0.02, y as f64 * 0.02, 0);
            // Box–Muller.
            let (u1, u2): (f32, f32) = (rng.random_range(1e-7..1.0), rng.random());
            v + sigma * (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
        });
        let est = estimate_noise_sigma(&img);
        assert!(
            (est - sigma).abs() <= 0.15 * sigma + 1e-3,
            "sigma {sigma}: estimated {est}"
        );
    }
}

#[test]
fn bad_dehazing_options_are_rejected() {
    let s = scene(2.0, 0.8, 0.3, &[[0.3, 0.0, 0.0]]);
    let v = s.views();
    let atm = AtmosphereParams {
        airlight: 0.8,
        beta: 0.3,
    };
    let run = |o: DehazingOptions| {
        field_of(
            build_cost_volume(
                &v[0],
                &v[1..],
                &planes(),
                CostKind::DehazingWith(atm, o),
                &Monitor::noop(),
            )
            .unwrap_err(),
        )
    };
    let base = DehazingOptions::default();
    assert_eq!(
        run(DehazingOptions {
            range: RangePenalty::Soft { k: -1.0 },
            ..base
        }),
        "options.range.k"
    );
    assert_eq!(
        run(DehazingOptions {
            noise_sigma: Some(f32::NAN),
            ..base
        }),
        "options.noise_sigma"
    );
}

/// Strips share one set of image copies; copies made from other views are refused, naming
/// `images`, and the right ones give the rows of the whole volume.
#[test]
fn image_copies_of_other_views_are_refused() {
    let s = scene(2.0, 0.8, 0.3, &[[0.3, 0.0, 0.0], [-0.25, 0.0, 0.0]]);
    let v = s.views();
    let (p, kind) = (planes(), CostKind::Ordinary);
    let images = SweepImages::new(&v[0], &v[1..], &p, kind).unwrap();
    let rows = 3..9;
    let run = |sources: &[View<'_>]| {
        build_cost_volume_rows_in(
            Vec::new(),
            &v[0],
            sources,
            &p,
            kind,
            rows.clone(),
            &images,
            &Monitor::noop(),
        )
    };
    assert_eq!(field_of(run(&v[1..2]).unwrap_err()), "images");
    let strip = run(&v[1..]).unwrap();
    let whole = build_cost_volume(&v[0], &v[1..], &p, kind, &Monitor::noop()).unwrap();
    for i in 0..p.num_planes {
        let want = &whole.plane(i)[rows.start * W..rows.end * W];
        assert_eq!(strip.plane(i), want, "plane {i}");
    }
}

/// `fill_cost_rows` writes the rows where its layout says, leaving the rest of the buffer as it
/// was, and refuses a buffer or layout that cannot hold them (naming `out`), rows outside the
/// reference (naming `rows`) and copies of other views (naming `images`).
#[test]
fn fill_cost_rows_writes_at_its_layout_and_refuses_what_does_not_fit() {
    let s = scene(2.0, 0.8, 0.3, &[[0.3, 0.0, 0.0], [-0.25, 0.0, 0.0]]);
    let v = s.views();
    let (p, kind) = (planes(), CostKind::Ordinary);
    let images = SweepImages::new(&v[0], &v[1..], &p, kind).unwrap();
    let whole = build_cost_volume(&v[0], &v[1..], &p, kind, &Monitor::noop()).unwrap();
    let n = p.num_planes;
    // Planes of 6 rows, the given 4 rows (image rows 5..9) written from row 2.
    let layout = RowsLayout {
        plane_stride: 6 * W,
        first_row: 2,
    };
    let fill = |out: &mut [f32], layout, rows: std::ops::Range<usize>, sources: &[View<'_>]| {
        fill_cost_rows(
            out,
            layout,
            &v[0],
            sources,
            &p,
            kind,
            rows,
            &images,
            &Monitor::noop(),
        )
    };
    let mut out = vec![-1.0f32; n * 6 * W];
    fill(&mut out, layout, 5..9, &v[1..]).unwrap();
    for i in 0..n {
        let plane = &out[i * 6 * W..(i + 1) * 6 * W];
        assert!(plane[..2 * W].iter().all(|&c| c == -1.0), "plane {i} kept");
        assert_eq!(&plane[2 * W..], &whole.plane(i)[5 * W..9 * W], "plane {i}");
    }
    let too_short = RowsLayout {
        plane_stride: 5 * W,
        first_row: 2,
    };
    let mut short = vec![0.0f32; n * 5 * W];
    assert_eq!(
        field_of(fill(&mut short, too_short, 5..9, &v[1..]).unwrap_err()),
        "out"
    );
    assert_eq!(
        field_of(fill(&mut out[1..], layout, 5..9, &v[1..]).unwrap_err()),
        "out"
    );
    assert_eq!(
        field_of(fill(&mut out, layout, 5..5, &v[1..]).unwrap_err()),
        "rows"
    );
    assert_eq!(
        field_of(fill(&mut out, layout, H - 2..H + 2, &v[1..]).unwrap_err()),
        "rows"
    );
    assert_eq!(
        field_of(fill(&mut out, layout, 5..9, &v[1..2]).unwrap_err()),
        "images"
    );
}
