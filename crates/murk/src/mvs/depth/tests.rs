use super::bands::*;
use super::sgm::{aggregate, directions, Guide, Penalties};
use super::*;
use crate::camera::Intrinsics;
use crate::mvs::cost_volume::census::{self, CensusImage, CensusSource};
use crate::mvs::pose::Pose;

/// Deterministic pseudo-random values in [0, 1).
fn lcg(seed: u64, n: usize) -> Vec<f32> {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32) / (1u64 << 24) as f32
        })
        .collect()
}

/// Straightforward SGM: one full path-cost volume per direction, explicit loops and minima.
fn reference_sgm(
    c: &[f32],
    (w, h, n): (usize, usize, usize),
    paths: usize,
    pen: &Penalties,
    guide: &ImageF32,
) -> Vec<f32> {
    let idx = |x: usize, y: usize, d: usize| (y * w + x) * n + d;
    let mut s = vec![0.0f32; w * h * n];
    for &(dx, dy) in directions(paths) {
        let mut l = vec![0.0f32; w * h * n];
        let ys: Vec<usize> = if dy >= 0 {
            (0..h).collect()
        } else {
            (0..h).rev().collect()
        };
        let xs: Vec<usize> = if dx >= 0 {
            (0..w).collect()
        } else {
            (0..w).rev().collect()
        };
        for &y in &ys {
            for &x in &xs {
                let (xp, yp) = (x as i64 - dx as i64, y as i64 - dy as i64);
                if xp < 0 || yp < 0 || xp >= w as i64 || yp >= h as i64 {
                    for d in 0..n {
                        l[idx(x, y, d)] = c[idx(x, y, d)];
                    }
                    continue;
                }
                let (xp, yp) = (xp as usize, yp as usize);
                let m = (0..n)
                    .map(|k| l[idx(xp, yp, k)])
                    .fold(f32::INFINITY, f32::min);
                let ch = guide.channels();
                let g: f32 = (0..ch)
                    .map(|k| (guide.get(x, y, k) - guide.get(xp, yp, k)).abs())
                    .sum::<f32>()
                    / ch as f32;
                let p2 = if pen.p2_gradient_scale > 0.0 {
                    (pen.p2 / (1.0 + g / pen.p2_gradient_scale)).max(pen.p1)
                } else {
                    pen.p2.max(pen.p1)
                };
                for d in 0..n {
                    let mut best = l[idx(xp, yp, d)];
                    if d > 0 {
                        best = best.min(l[idx(xp, yp, d - 1)] + pen.p1);
                    }
                    if d + 1 < n {
                        best = best.min(l[idx(xp, yp, d + 1)] + pen.p1);
                    }
                    best = best.min(m + p2);
                    l[idx(x, y, d)] = c[idx(x, y, d)] + best - m;
                }
            }
        }
        for (si, li) in s.iter_mut().zip(&l) {
            *si += li;
        }
    }
    s
}

#[test]
fn fast_sgm_equals_reference() {
    // Width > PIXEL_CHUNK so row sweeps split rows across several tasks; plane counts cover
    // the unrolled path step's full chunks with and without a remainder, and short curves.
    let (w, h) = (37, 9);
    for (n, paths, tau) in [
        (7, 8, 0.05f32),
        (5, 4, 0.0),
        (9, 5, 0.05),
        (33, 5, 0.0),
        (1, 8, 0.1),
        (2, 8, 0.05),
        (27, 8, 0.05),
        (18, 4, 0.0),
    ] {
        let c: Vec<f32> = lcg(n as u64, w * h * n).iter().map(|v| 3.0 * v).collect();
        let guide = ImageF32::from_vec(w, h, 3, lcg(99, w * h * 3)).unwrap();
        let pen = Penalties {
            p1: 0.1,
            p2: 0.9,
            p2_gradient_scale: tau,
        };
        let fast = aggregate(
            &c,
            w,
            h,
            n,
            paths,
            &pen,
            Some(Guide::new(&guide)),
            &Monitor::noop(),
        )
        .unwrap();
        let slow = reference_sgm(&c, (w, h, n), paths, &pen, &guide);
        for (i, (a, b)) in fast.iter().zip(&slow).enumerate() {
            assert!(
                (a - b).abs() <= 1e-4 * b.abs().max(1.0),
                "voxel {i}: {a} vs {b}"
            );
        }
    }
}

/// [`sgm::OnePass`], fed a row at a time, gives [`aggregate`]'s 5-path sums bit for bit, in `f32`
/// and in `u16` levels, with and without the adaptive `P2`, from the first row or from a later
/// one (its guide rows then numbered from that row, as a stripe's are), with pixels split
/// across several tasks (`w` > the row sweep's chunk).
#[test]
fn one_pass_rows_equal_the_five_path_aggregation() {
    fn check<T: sgm::PathCost>(c: &[T], guide: &ImageF32, (w, h, n): (usize, usize, usize)) {
        let isa = crate::cpu::Isa::detect();
        for tau in [0.0f32, 0.05] {
            let pen = Penalties {
                p1: 3.0,
                p2: 40.0,
                p2_gradient_scale: tau,
            };
            for y0 in [0, 3] {
                let rows = &c[y0 * w * n..];
                let g = Guide::rows(guide, y0..h);
                let whole =
                    aggregate(rows, w, h - y0, n, 5, &pen, Some(g), &Monitor::noop()).unwrap();
                let mut pass = sgm::OnePass::new(w, n, isa);
                let mut sum = vec![T::ZERO; w * n];
                for (y, (crow, expected)) in rows
                    .chunks_exact(w * n)
                    .zip(whole.chunks_exact(w * n))
                    .enumerate()
                {
                    pass.row(crow, &mut sum, y, &pen, Some(g));
                    assert!(sum == expected, "row {y} from {y0}, tau {tau}, n {n}");
                }
            }
        }
    }
    let (w, h) = (37, 9);
    let guide = ImageF32::from_vec(w, h, 3, lcg(99, w * h * 3)).unwrap();
    for n in [1usize, 7, 33] {
        let c = lcg(n as u64, w * h * n);
        let floats: Vec<f32> = c.iter().map(|v| 30.0 * v).collect();
        let levels: Vec<u16> = c.iter().map(|v| (4000.0 * v) as u16).collect();
        check(&floats, &guide, (w, h, n));
        check(&levels, &guide, (w, h, n));
    }
}

/// [`sgm::OnePass`] over rows whose planes change ([`sgm::OnePass::set_planes`]: narrower,
/// wider, shifted, disjoint) is the 5-path recursion written out plane by plane in the set's
/// indices, where the steps from the previous pixel stay inside the planes both rows search and
/// every other plane is reached only by the jump `min_k L(p−r, k) + P2`, for every instruction
/// set.
#[test]
fn one_pass_over_changing_windows_is_the_recursion_with_unsearched_planes_unreachable() {
    let (w, h, all) = (41, 10, 40usize);
    let windows: [std::ops::Range<usize>; 10] = [
        0..40,
        0..40,
        5..20,
        5..20,
        10..33,
        30..40,
        0..3,
        2..37,
        2..37,
        17..18,
    ];
    let (p1, p2) = (40u16, 900u16);
    let pen = Penalties {
        p1: f32::from(p1),
        p2: f32::from(p2),
        p2_gradient_scale: 0.0,
    };
    // Levels of every plane of the set; a row reads its window's.
    let c: Vec<u16> = lcg(5, w * h * all)
        .iter()
        .map(|v| (v * 4000.0) as u16)
        .collect();
    let cost = |x: usize, y: usize, g: usize| c[(y * w + x) * all + g];
    // The recursion, one direction at a time, in the set's plane indices.
    let mut expected: Vec<Vec<u32>> = (0..h).map(|y| vec![0; w * windows[y].len()]).collect();
    for (dx, dy) in sgm::ONE_PASS_DIRECTIONS {
        let mut l: Vec<Vec<u16>> = (0..h).map(|y| vec![0; w * windows[y].len()]).collect();
        for y in 0..h {
            let xs: Vec<usize> = if dx >= 0 {
                (0..w).collect()
            } else {
                (0..w).rev().collect()
            };
            let win = windows[y].clone();
            let n = win.len();
            for x in xs {
                let (xp, yp) = (x as i64 - i64::from(dx), y as i64 - i64::from(dy));
                let inside = xp >= 0 && xp < w as i64 && yp >= 0;
                for (i, g) in win.clone().enumerate() {
                    let v = if !inside {
                        cost(x, y, g)
                    } else {
                        let (xp, yp) = (xp as usize, yp as usize);
                        let pw = windows[yp].clone();
                        let prev = &l[yp][xp * pw.len()..(xp + 1) * pw.len()];
                        // Only planes both rows search: a ±1 step from outside this row's window
                        // is not taken either.
                        let both = |k: i64| {
                            k >= pw.start.max(win.start) as i64 && k < pw.end.min(win.end) as i64
                        };
                        let at = |k: i64| -> u16 {
                            if both(k) {
                                prev[k as usize - pw.start]
                            } else {
                                u16::MAX
                            }
                        };
                        let prev_min = *prev.iter().min().unwrap();
                        let g = g as i64;
                        let m = at(g)
                            .min(at(g - 1).min(at(g + 1)).saturating_add(p1))
                            .min(prev_min.saturating_add(p2));
                        cost(x, y, g as usize).saturating_add(m - prev_min)
                    };
                    l[y][x * n + i] = v;
                    expected[y][x * n + i] += u32::from(v);
                }
            }
        }
    }
    for (no_avx512, scalar) in [(false, false), (true, false), (true, true)] {
        crate::cpu::force_no_avx512(no_avx512);
        crate::cpu::force_scalar(scalar);
        let isa = crate::cpu::Isa::detect();
        let mut pass = sgm::OnePass::new(w, all, isa);
        for (y, win) in windows.iter().enumerate() {
            pass.set_planes(win.clone());
            let crow: Vec<u16> = (0..w)
                .flat_map(|x| win.clone().map(move |g| (x, g)))
                .map(|(x, g)| cost(x, y, g))
                .collect();
            let mut sum = vec![0u16; w * win.len()];
            pass.row(&crow, &mut sum, y, &pen, None);
            let want: Vec<u16> = expected[y].iter().map(|&v| v as u16).collect();
            assert!(
                sum == want,
                "row {y}, window {win:?}, no_avx512 {no_avx512}, scalar {scalar}"
            );
        }
    }
    crate::cpu::force_no_avx512(false);
    crate::cpu::force_scalar(false);
}

/// The `u16` aggregation gives the same sums bit for bit through its AVX-512 copy (masked
/// 32-lane chunks), the AVX2 copy and the plain loops, for curves shorter than, equal to and
/// longer than a chunk, with and without a masked last chunk, and with levels near the top of
/// the range (where the saturating additions matter).
#[test]
fn u16_aggregation_is_the_same_in_every_instruction_set() {
    let (w, h) = (37, 7);
    for n in [1usize, 2, 15, 16, 17, 31, 32, 33, 64, 173] {
        for top in [4000u16, 60000] {
            let c: Vec<u16> = lcg(n as u64 + u64::from(top), w * h * n)
                .iter()
                .map(|v| (v * f32::from(top)) as u16)
                .collect();
            let guide = ImageF32::from_vec(w, h, 3, lcg(7, w * h * 3)).unwrap();
            let pen = Penalties {
                p1: 40.0,
                p2: 900.0,
                p2_gradient_scale: 0.05,
            };
            let run = |no_avx512: bool, scalar: bool| {
                crate::cpu::force_no_avx512(no_avx512);
                crate::cpu::force_scalar(scalar);
                let s = aggregate(
                    &c,
                    w,
                    h,
                    n,
                    8,
                    &pen,
                    Some(Guide::new(&guide)),
                    &Monitor::noop(),
                )
                .unwrap();
                crate::cpu::force_no_avx512(false);
                crate::cpu::force_scalar(false);
                s
            };
            let widest = run(false, false);
            assert_eq!(widest, run(true, false), "AVX2 copy, {n} planes, top {top}");
            assert_eq!(
                widest,
                run(true, true),
                "plain loops, {n} planes, top {top}"
            );
        }
    }
}

#[test]
fn sub_plane_refinement_recovers_fractional_minimum() {
    let n = 32;
    let m = 10.3f32;
    let curve: Vec<f32> = (0..n)
        .map(|i| 0.01 * (i as f32 - m).powi(2) + 0.2)
        .collect();
    let sel = select_curve(&curve, 0.0);
    assert!((sel.index - m).abs() < 1e-3, "{sel:?}");
    assert!(sel.confidence > 0.0 && sel.confidence <= 1.0);
    // Through the whole pipeline: with P1 = P2 = 0 every path cost equals the raw cost, so
    // the aggregated curve is 8× the parabola and the refinement is exact again.
    let (w, h) = (5, 4);
    let planes = PlaneSet::new(1.0, 10.0, n).unwrap();
    let mut data = Vec::with_capacity(w * h * n);
    for &c in &curve {
        data.extend(std::iter::repeat_n(c, w * h));
    }
    let params = DepthParams {
        sgm: SgmParams {
            p1: 0.0,
            p2: 0.0,
            ..SgmParams::default()
        },
        matching: MatchingParams {
            cost_window_radius: 0,
            ..MatchingParams::default()
        },
        ..DepthParams::default()
    };
    let guide = ImageF32::filled(w, h, 3, 0.5);
    let r = depth_from_costs(data, w, h, &planes, &guide, &params, &Monitor::noop()).unwrap();
    let want = planes.inverse_depth(f64::from(m));
    // SGM aggregates the curve as integer levels (`quantise`, 13 bits here): the vertex moves
    // by 0.006 plane here, not more.
    let plane_step = planes.inverse_depth(1.0) - planes.inverse_depth(0.0);
    for (&inv, &z) in r.inverse_depth.data().iter().zip(r.z_depth.data()) {
        assert!(
            (f64::from(inv) - want).abs() < 0.015 * plane_step.abs(),
            "{inv} vs {want}"
        );
        assert!((z * inv - 1.0).abs() < 1e-6, "z {z} is not 1 / {inv}");
    }
    // Minimum at the first plane: no refinement, index exactly 0.
    let edge: Vec<f32> = (0..n).map(|i| i as f32).collect();
    assert_eq!(select_curve(&edge, 0.0).index, 0.0);
    // A flat curve has zero confidence.
    assert_eq!(select_curve(&[1.0; 8], 0.0).confidence, 0.0);
}

#[test]
fn params_validation_names_fields() {
    let field = |p: DepthParams| match p.validate() {
        Err(MurkError::InvalidArgument { field, .. }) => field,
        other => panic!("{other:?}"),
    };
    let d = DepthParams::default();
    d.validate().unwrap();
    assert_eq!(
        field(DepthParams {
            sgm: SgmParams { p1: -1.0, ..d.sgm },
            ..d
        }),
        "p1"
    );
    assert_eq!(
        field(DepthParams {
            sgm: SgmParams {
                p2: d.sgm.p1 / 2.0,
                ..d.sgm
            },
            ..d
        }),
        "p2"
    );
    assert_eq!(
        field(DepthParams {
            sgm: SgmParams {
                num_paths: 6,
                ..d.sgm
            },
            ..d
        }),
        "num_paths"
    );
    assert_eq!(
        field(DepthParams {
            matching: MatchingParams {
                cost_window_radius: 99,
                ..d.matching
            },
            ..d
        }),
        "cost_window_radius"
    );
    assert_eq!(
        field(DepthParams {
            post_filter: PostFilter::WeightedMedian {
                radius: 2,
                sigma: 0.0
            },
            ..d
        }),
        "post_filter.sigma"
    );
    let planes = PlaneSet::new(1.0, 2.0, 4).unwrap();
    let g = ImageF32::filled(3, 3, 3, 0.0);
    match depth_from_costs(vec![0.0; 5], 3, 3, &planes, &g, &d, &Monitor::noop()) {
        Err(MurkError::InvalidArgument { field, .. }) => assert_eq!(field, "costs"),
        other => panic!("{other:?}"),
    }
    // Negative and non-finite costs would be clamped by the quantisation: refused instead.
    for bad in [-0.5, f32::NAN, f32::INFINITY] {
        let mut costs = vec![0.25; 36];
        costs[7] = bad;
        match depth_from_costs(costs, 3, 3, &planes, &g, &d, &Monitor::noop()) {
            Err(MurkError::InvalidArgument { field, reason }) => {
                assert_eq!(field, "costs");
                assert!(reason.contains(">= 0"), "{reason}");
            }
            other => panic!("{bad}: {other:?}"),
        }
    }
}

// --- Rendered planes ------------------------------------------------------------------------

const W: usize = 80;
const H: usize = 60;

fn k() -> Intrinsics {
    Intrinsics::new(80.0, 80.0, 39.5, 29.5)
}

/// Smooth aperiodic RGB texture on world coordinates (x, y), values in [0.05, 0.95].
fn texture(x: f64, y: f64, c: usize) -> f32 {
    let cf = c as f64;
    // Wavelengths of ~0.2–0.5 scene units: several pixels at z = 3…6, so no aliasing.
    let (x, y) = (x * 0.5, y * 0.5);
    let a = (x * (31.0 + 7.0 * cf) + y * (11.0 - 5.0 * cf) + cf).sin();
    let b = (x * (-13.0 + 3.0 * cf) + y * (29.0 + 4.0 * cf) + 2.0 * cf).sin();
    let d = (x * 17.0 * (1.0 + 0.3 * cf) - y * 19.0 + 0.5).sin() * (y * 7.0 + x * 3.0).cos();
    (0.5 + 0.45 * (a + b + d) / 3.0) as f32
}

/// Renders the plane `z = z0 + slope·x` (world = reference frame) from a camera at `centre`
/// (no rotation); texture only where `x < textured_below_x`, flat grey elsewhere.
fn render(centre: [f64; 3], z0: f64, slope: f64, textured_below_x: f64) -> (ImageF32, ImageF32) {
    let kk = k();
    let mut img = ImageF32::filled(W, H, 3, 0.0);
    let mut z = ImageF32::filled(W, H, 1, 0.0);
    for v in 0..H {
        for u in 0..W {
            let r = kk.ray(u as f64, v as f64);
            let d = [r[0] / r[2], r[1] / r[2], 1.0];
            // (c_z + λ) = z0 + slope (c_x + λ d_x)
            let lambda = (z0 + slope * centre[0] - centre[2]) / (1.0 - slope * d[0]);
            let (x, y) = (centre[0] + lambda * d[0], centre[1] + lambda * d[1]);
            for c in 0..3 {
                let t = if x < textured_below_x {
                    texture(x, y, c)
                } else {
                    0.45
                };
                img.set(u, v, c, t);
            }
            z.set(u, v, 0, lambda as f32);
        }
    }
    (img, z)
}

struct Rig {
    images: Vec<ImageF32>,
    depth: ImageF32,
    poses: Vec<Pose>,
}

fn rig(z0: f64, slope: f64, textured_below_x: f64) -> Rig {
    let centres = [
        [0.0, 0.0, 0.0],
        [0.25, 0.0, 0.0],
        [-0.25, 0.0, 0.0],
        [0.0, 0.2, 0.0],
    ];
    let mut images = Vec::new();
    let mut poses = Vec::new();
    let mut depth = None;
    for c in centres {
        let (img, z) = render(c, z0, slope, textured_below_x);
        depth.get_or_insert(z);
        images.push(img);
        poses.push(Pose::translation_only([-c[0], -c[1], -c[2]]).unwrap());
    }
    Rig {
        images,
        depth: depth.unwrap(),
        poses,
    }
}

/// Views of `images` from the rig's cameras `poses`, the reference first.
fn views_of<'a>(images: &'a [ImageF32], poses: &[Pose]) -> Vec<View<'a>> {
    images
        .iter()
        .zip(poses)
        .map(|(image, pose)| View {
            image,
            intrinsics: k(),
            pose: *pose,
        })
        .collect()
}

fn run(rig: &Rig, planes: &PlaneSet, params: &DepthParams) -> DepthResult {
    let views = views_of(&rig.images, &rig.poses);
    estimate_depth(
        &views[0],
        &views[1..],
        planes,
        CostKind::Ordinary,
        params,
        &Monitor::noop(),
    )
    .unwrap()
}

/// Share of interior pixels (4 px margin) whose inverse depth is within one plane spacing.
fn share_within(r: &DepthResult, gt: &ImageF32, planes: &PlaneSet, spacings: f64) -> f64 {
    let step = spacings * planes.inverse_depth_step();
    let (mut good, mut n) = (0usize, 0usize);
    for y in 4..H - 4 {
        for x in 4..W - 4 {
            let inv = f64::from(r.inverse_depth.get(x, y, 0));
            let want = 1.0 / f64::from(gt.get(x, y, 0));
            n += 1;
            if (inv - want).abs() <= step {
                good += 1;
            }
        }
    }
    good as f64 / n as f64
}

#[test]
fn recovers_fronto_parallel_and_slanted_planes() {
    let planes = PlaneSet::new(2.0, 10.0, 64).unwrap();
    for (z0, slope) in [(4.0, 0.0), (3.0, 0.0), (4.0, 0.4)] {
        let rig = rig(z0, slope, f64::INFINITY);
        for params in [
            DepthParams::default(),
            DepthParams {
                post_filter: PostFilter::WeightedMedian {
                    radius: 2,
                    sigma: 0.1,
                },
                ..DepthParams::default()
            },
        ] {
            let r = run(&rig, &planes, &params);
            let s1 = share_within(&r, &rig.depth, &planes, 1.0);
            let s2 = share_within(&r, &rig.depth, &planes, 2.0);
            eprintln!(
                "z0 {z0} slope {slope} {:?}: within 1 plane {s1:.3}, 2 planes {s2:.3}",
                params.post_filter
            );
            assert!(s1 > 0.95, "z0 {z0} slope {slope} {params:?}: {s1}");
            assert!(r.confidence.data().iter().all(|c| (0.0..=1.0).contains(c)));
        }
    }
}

#[test]
fn confidence_high_on_texture_low_on_flat() {
    let planes = PlaneSet::new(2.0, 10.0, 64).unwrap();
    // The plane at z = 4 is textured for world x < 0 (left half of the reference image).
    let rig = rig(4.0, 0.0, 0.0);
    // Without smoothness penalties the aggregated curve is the (windowed) data term summed over
    // paths, so the confidence measures the data's evidence alone; with penalties SGM rightly
    // propagates the textured half's depth into the flat half and becomes confident there too.
    let params = DepthParams {
        sgm: SgmParams {
            p1: 0.0,
            p2: 0.0,
            ..SgmParams::default()
        },
        ..DepthParams::default()
    };
    let r = run(&rig, &planes, &params);
    let median = |x0: usize, x1: usize| {
        let mut v: Vec<f32> = (8..H - 8)
            .flat_map(|y| (x0..x1).map(move |x| (x, y)))
            .map(|(x, y)| r.confidence.get(x, y, 0))
            .collect();
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    };
    let (tex, flat) = (median(4, W / 2 - 10), median(W / 2 + 10, W - 4));
    assert!(tex > 0.3 && flat < 0.5 * tex, "textured {tex}, flat {flat}");
}

/// The bound that quantises a strip before its costs exist holds every weighted voxel of each
/// cost kind, with the census term and without, on hazy views of the test rig (whose sources see
/// only part of the reference at the near planes, so out-of-view penalties are among the voxels):
/// no cost takes the top level by truncation. Without weights the bound is reached where a voxel
/// that no source sees holds the penalty `γ`.
#[test]
fn cost_bound_holds_every_weighted_cost() {
    use crate::atmosphere::AtmosphereParams;
    use crate::mvs::cost_volume::{build_cost_volume, DehazingOptions};
    let rig = rig(4.0, 0.3, f64::INFINITY);
    let atm = AtmosphereParams {
        airlight: 0.8,
        beta: 0.2,
    };
    // The views hazed with the rig's depth seen from the reference (enough for the bound).
    let hazy: Vec<ImageF32> = rig
        .images
        .iter()
        .map(|img| {
            let mut out = img.clone();
            for y in 0..H {
                for x in 0..W {
                    let t = (-0.2 * rig.depth.get(x, y, 0)).exp();
                    for c in 0..3 {
                        out.set(x, y, c, img.get(x, y, c) * t + 0.8 * (1.0 - t));
                    }
                }
            }
            out
        })
        .collect();
    let views = views_of(&hazy, &rig.poses);
    let planes = PlaneSet::new(1.0, 10.0, 48).unwrap();
    let params = DepthParams::default();
    let weights = contrast_weights_of(views[0].image, &params);
    let w_max = weights.iter().copied().fold(1.0f32, f32::max);
    assert!(w_max > 1.0, "the rig's contrast weights reach above 1");
    let codes = census::census_transform(views[0].image);
    let source_codes: Vec<CensusImage> = views[1..]
        .iter()
        .map(|v| census::census_transform(v.image))
        .collect();
    let census_sources: Vec<CensusSource<'_>> = views[1..]
        .iter()
        .zip(&source_codes)
        .map(|(v, c)| CensusSource {
            census: c,
            intrinsics: v.intrinsics,
            relative: Pose::relative(&views[0].pose, &v.pose),
        })
        .collect();
    for kind in [
        CostKind::Ordinary,
        CostKind::Dehazing(atm),
        CostKind::DehazingWith(atm, DehazingOptions::default()),
    ] {
        for census_weight in [0.0f32, 1.5] {
            let mut data =
                build_cost_volume(&views[0], &views[1..], &planes, kind, &Monitor::noop())
                    .unwrap()
                    .into_vec();
            if census_weight > 0.0 {
                census::add_census_costs(
                    &mut data,
                    &codes,
                    &k(),
                    &census_sources,
                    &planes,
                    0..H,
                    census_weight,
                    &weights,
                    &Monitor::noop(),
                )
                .unwrap();
            }
            let largest = window::largest_weighted(&data, &weights, W, H, planes.num_planes);
            let bound = cost_bound(3, &weights, census_weight);
            assert!(
                largest <= bound * (1.0 + 1e-6),
                "{kind:?} census {census_weight}: {largest} > {bound}"
            );
            // With one source, the near planes' voxels it does not see hold exactly γ: the
            // unweighted bound is reached.
            if census_weight == 0.0 {
                let one =
                    build_cost_volume(&views[0], &views[1..2], &planes, kind, &Monitor::noop())
                        .unwrap()
                        .into_vec();
                let largest = window::largest_weighted(&one, &[], W, H, planes.num_planes);
                assert_eq!(largest, cost_bound(3, &[], 0.0), "{kind:?}");
            }
        }
    }
}

/// The depth does not depend on the bands a strip is built in: bands of a few rows (whose
/// windows' rows are moved from band to band, or computed again with the census term) give the
/// one-band depth bit for bit, in one strip and in several.
#[test]
fn bands_do_not_change_the_depth() {
    use crate::atmosphere::AtmosphereParams;
    use crate::mvs::cost_volume::DehazingOptions;
    let rig = rig(4.0, 0.3, f64::INFINITY);
    let views = views_of(&rig.images, &rig.poses);
    let planes = PlaneSet::new(2.0, 10.0, 64).unwrap();
    let atm = AtmosphereParams {
        airlight: 0.8,
        beta: 0.1,
    };
    for num_paths in [8, 5] {
        for (kind, census_weight, budget) in [
            (CostKind::Ordinary, 0.0, 96),
            (
                CostKind::DehazingWith(atm, DehazingOptions::default()),
                0.0,
                96,
            ),
            (CostKind::Dehazing(atm), 1.0, 96),
            (CostKind::Ordinary, 0.0, 1),
        ] {
            let params = DepthParams {
                sgm: SgmParams {
                    volume_budget_mib: budget,
                    num_paths,
                    ..SgmParams::default()
                },
                matching: MatchingParams {
                    census_weight,
                    ..MatchingParams::default()
                },
                ..DepthParams::default()
            };
            let depth = |band_rows, stripe_rows| {
                let layout = Layout {
                    band_rows,
                    stripe_rows,
                    volumes: false,
                };
                rig_depth(&views, &planes, kind, &params, layout)
            };
            // 1 MiB: strips of 16 own rows (the volume is 1.2 MiB); one pass: stripes of 20.
            assert_eq!(strips_of(W, H, 64, budget).len() > 1, budget == 1);
            let stripes = (budget == 1).then_some(20);
            let whole = depth(Some(H), stripes);
            for rows in [1, 3, 5, 8, 13] {
                let banded = depth(Some(rows), stripes);
                let what = format!("{num_paths} paths, {kind:?}, {rows} rows");
                assert_eq!(banded.z_depth.data(), whole.z_depth.data(), "{what}");
                assert_eq!(banded.confidence.data(), whole.confidence.data(), "{what}");
            }
        }
    }
}

/// [`estimate_depth_in_bands`] of the rig's `views` (the first the reference) laid out as
/// `layout`.
fn rig_depth(
    views: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    params: &DepthParams,
    layout: Layout,
) -> DepthResult {
    let monitor = Monitor::noop();
    estimate_depth_in_bands(
        &views[0],
        &views[1..],
        planes,
        kind,
        params,
        &DepthPrior::default(),
        layout,
        &monitor,
    )
    .unwrap()
}

/// The one pass streams rows into exactly the depth that aggregating the whole levels volume
/// with the same 5 paths gives, where both see the image whole (one stripe, one strip): the
/// same costs, window, quantiser, sums, claims and selections.
#[test]
fn one_pass_streams_what_the_volumes_aggregate() {
    use crate::atmosphere::AtmosphereParams;
    let rig = rig(4.0, 0.3, 60.0);
    let views = views_of(&rig.images, &rig.poses);
    let planes = PlaneSet::new(2.0, 10.0, 48).unwrap();
    let atm = AtmosphereParams {
        airlight: 0.8,
        beta: 0.1,
    };
    for (kind, census_weight) in [
        (CostKind::Ordinary, 0.0),
        (CostKind::Dehazing(atm), 0.0),
        (CostKind::Dehazing(atm), 1.0),
    ] {
        let params = DepthParams {
            sgm: SgmParams {
                num_paths: 5,
                ..SgmParams::default()
            },
            matching: MatchingParams {
                census_weight,
                ..MatchingParams::default()
            },
            ..DepthParams::default()
        };
        let depth = |volumes| {
            let layout = Layout {
                volumes,
                ..Layout::default()
            };
            rig_depth(&views, &planes, kind, &params, layout)
        };
        let (streamed, volumes) = (depth(false), depth(true));
        assert_eq!(streamed.z_depth.data(), volumes.z_depth.data(), "{kind:?}");
        assert_eq!(
            streamed.confidence.data(),
            volumes.confidence.data(),
            "{kind:?}"
        );
    }
}

/// Plane windows ([`PlaneWindows`]) restrict each row's search: windows of every plane change
/// nothing (bit for bit, in one group or several), windows around each group's true depths keep
/// the accuracy, and windows away from the truth hold every confident pixel's plane inside
/// its row's window.
#[test]
fn plane_windows_restrict_each_rows_search() {
    let rig = rig(4.0, 0.4, f64::INFINITY);
    let views = views_of(&rig.images, &rig.poses);
    let planes = PlaneSet::new(2.0, 10.0, 64).unwrap();
    let params = DepthParams::default();
    assert_eq!(params.sgm.num_paths, 5, "windows apply to the one pass");
    let run = |windows: Option<&PlaneWindows>| {
        let prior = DepthPrior {
            windows,
            ..DepthPrior::default()
        };
        estimate_depth_in_bands(
            &views[0],
            &views[1..],
            &planes,
            CostKind::Ordinary,
            &params,
            &prior,
            Layout::default(),
            &Monitor::noop(),
        )
        .unwrap()
    };
    let free = run(None);
    for every in [
        PlaneWindows::whole(64, H).unwrap(),
        PlaneWindows::new(8, vec![0..64; H.div_ceil(8)]).unwrap(),
    ] {
        let same = run(Some(&every));
        assert_eq!(same.z_depth.data(), free.z_depth.data());
        assert_eq!(same.confidence.data(), free.confidence.data());
    }

    // Each group of 8 rows: its true planes and 3 more on each side.
    let group = 8;
    let around: Vec<std::ops::Range<usize>> = (0..H.div_ceil(group))
        .map(|g| {
            let index = |x: usize, y: usize| {
                planes.index_of_inverse_depth(1.0 / f64::from(rig.depth.get(x, y, 0)))
            };
            let rows = g * group..((g + 1) * group).min(H);
            let (lo, hi) = rows
                .flat_map(|y| (0..W).map(move |x| (x, y)))
                .map(|(x, y)| index(x, y))
                .fold((f64::MAX, f64::MIN), |(a, b), i| (a.min(i), b.max(i)));
            (lo.floor() as usize).saturating_sub(3)..((hi.ceil() as usize) + 4).min(64)
        })
        .collect();
    let around = PlaneWindows::new(group, around).unwrap();
    assert!(around.planes_searched(H) < H * 64 * 3 / 4, "{around:?}");
    let narrow = run(Some(&around));
    let (a, b) = (
        share_within(&narrow, &rig.depth, &planes, 1.0),
        share_within(&free, &rig.depth, &planes, 1.0),
    );
    assert!(a >= b - 0.01, "around the truth {a}, every plane {b}");

    // Away from the truth (true planes 13–44): the far planes above, the near ones below.
    let half = H.div_ceil(group) / 2;
    let away: Vec<std::ops::Range<usize>> = (0..H.div_ceil(group))
        .map(|g| if g < half { 0..12 } else { 50..64 })
        .collect();
    let away = PlaneWindows::new(group, away).unwrap();
    let missed = run(Some(&away));
    let mut confident = 0;
    for y in 0..H {
        let window = away.of_row(y);
        for x in 0..W {
            if missed.confidence.get(x, y, 0) <= 0.0 {
                continue;
            }
            confident += 1;
            let i = planes.index_of_inverse_depth(f64::from(missed.inverse_depth.get(x, y, 0)));
            assert!(
                i >= window.start as f64 - 0.5 && i <= (window.end - 1) as f64 + 0.5,
                "({x}, {y}): plane {i} outside {window:?}"
            );
        }
    }
    assert!(confident > 0, "some pixels are confident");
}

/// The one pass's stripes partition the image in order, each aggregating its own rows and the
/// overlap above them, and all about the same number of rows.
#[test]
fn one_pass_stripes_partition_the_image_evenly() {
    assert_eq!(
        one_pass_stripes(480, 256),
        vec![
            Strip {
                rows: 0..252,
                core: 0..252
            },
            Strip {
                rows: 228..480,
                core: 252..480
            },
        ]
    );
    for h in [1usize, 5, 24, 60, 192, 255, 256, 257, 480, 1080, 2160] {
        for stripe_rows in [1usize, 10, 32, 256] {
            let stripes = one_pass_stripes(h, stripe_rows);
            let mut next = 0;
            for s in &stripes {
                assert_eq!(s.core.start, next, "{h} {stripe_rows}: {stripes:?}");
                assert!(!s.core.is_empty() && s.core.end <= h);
                assert_eq!(
                    s.rows,
                    s.core.start.saturating_sub(STRIP_OVERLAP_ROWS)..s.core.end
                );
                next = s.core.end;
            }
            assert_eq!(next, h, "{h} {stripe_rows}");
            let sizes: Vec<usize> = stripes.iter().map(|s| s.rows.len()).collect();
            let (lo, hi) = (sizes.iter().min().unwrap(), sizes.iter().max().unwrap());
            // The last stripe may be short; the others differ by at most one row, unless the
            // stripes are shorter than the overlap (then each decides one row).
            let full = &sizes[..sizes.len() - 1];
            if stripe_rows > STRIP_OVERLAP_ROWS && !full.is_empty() {
                let (a, b) = (full.iter().min().unwrap(), full.iter().max().unwrap());
                assert!(b - a <= 1, "{h} {stripe_rows}: {sizes:?}");
            }
            assert!(hi >= lo);
        }
    }
}

/// Stripes of the one pass (paths started [`STRIP_OVERLAP_ROWS`] rows above each stripe's own
/// rows instead of at the image's top) change the depth little: within one plane step at
/// nearly every pixel.
#[test]
fn one_pass_stripes_match_one_stripe() {
    let rig = rig(4.0, 0.3, 60.0);
    let views = views_of(&rig.images, &rig.poses);
    let planes = PlaneSet::new(2.0, 10.0, 48).unwrap();
    let params = DepthParams {
        sgm: SgmParams {
            num_paths: 5,
            ..SgmParams::default()
        },
        ..DepthParams::default()
    };
    let depth = |stripe_rows| {
        let layout = Layout {
            stripe_rows,
            ..Layout::default()
        };
        rig_depth(&views, &planes, CostKind::Ordinary, &params, layout)
    };
    let whole = depth(None);
    let tol = planes.inverse_depth_step() as f32;
    for stripe_rows in [10, 15, 32] {
        let striped = depth(Some(stripe_rows));
        let n = whole.inverse_depth.data().len();
        let same = whole
            .inverse_depth
            .data()
            .iter()
            .zip(striped.inverse_depth.data())
            .filter(|(a, b)| (*a - *b).abs() <= tol)
            .count();
        assert!(same as f64 >= 0.95 * n as f64, "{stripe_rows}: {same}/{n}");
    }
}

/// Bands of a strip take a quarter of the budget (at most 32 MiB) with their window rows, and
/// at least 8 own rows.
#[test]
fn bands_fit_a_quarter_of_the_budget() {
    for (w, n, r, mib) in [
        (640, 173, 2, 96),
        (256, 256, 2, 96),
        (4000, 256, 16, 1024),
        (640, 480, 0, 1),
    ] {
        let rows = band_rows_of(w, n, r, mib);
        assert!(rows >= 8);
        if rows > 8 {
            let bytes = (rows + 2 * r) * w * n * 4;
            assert!(
                bytes <= ((mib << 20) / 4).min(32 << 20),
                "{w}x{n} r={r} {mib} MiB: {rows} rows"
            );
        }
    }
}

/// Strips partition the rows, each strip's volume covers its own rows plus the overlap, and a
/// volume within the budget is one strip without overlap.
#[test]
fn strips_partition_the_rows_within_the_budget() {
    assert_eq!(
        strips_of(100, 50, 10, 1),
        vec![Strip {
            rows: 0..50,
            core: 0..50
        }]
    );
    for (w, h, n, mib) in [(640, 480, 173, 64), (160, 120, 64, 1), (640, 480, 256, 1)] {
        let strips = strips_of(w, h, n, mib);
        assert!(strips.len() > 1);
        let mut next = 0;
        for s in &strips {
            assert_eq!(s.core.start, next);
            next = s.core.end;
            assert_eq!(
                s.rows.start,
                s.core.start.saturating_sub(STRIP_OVERLAP_ROWS)
            );
            assert_eq!(s.rows.end, (s.core.end + STRIP_OVERLAP_ROWS).min(h));
            assert!(!s.core.is_empty());
            // Within the budget unless it holds fewer than 16 own rows plus the overlap (the
            // floor on a strip's own rows).
            if (mib << 20) / (w * n * 4) >= 16 + 2 * STRIP_OVERLAP_ROWS {
                assert!(s.rows.len() * w * n * 4 <= mib << 20, "{s:?}");
            }
        }
        assert_eq!(next, h);
    }
}

/// A source's relative fall-off at an end of its searched range gets a warning that names the
/// source; one inside the range gets none.
#[test]
fn a_relative_falloff_at_its_bound_is_reported() {
    let warnings = bound_warnings(&[1.0; 6], 3, 0.0, &[-0.6, 0.1]);
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(warnings[0].starts_with("source 0: "), "{}", warnings[0]);
    assert!(warnings[0].contains("-0.600"), "{}", warnings[0]);
    assert!(!warnings[0].contains("  "), "{}", warnings[0]);
}
