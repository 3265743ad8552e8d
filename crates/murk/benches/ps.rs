//! Photometric stereo in turbid media on the reference's synthetic setting: a 300×300
//! sphere, β = σ = 5e-3 /mm, 8 lights, kernel support r = 81, initialised as a plane. Benches
//! the kernel build K̂ alone on the true sphere in both layouts (exact r×r window per pixel, and
//! murk's default: exact near block + 3×3-pixel cells beyond it) with each far-field model and
//! with Eq. 4.41's isotropic facet, the default build on the initial plane (the first
//! iteration's kernel), one 8-light BiCGStab solve of Eq. 4.52 alone on the default kernel, the
//! perspective normal integration alone, and the whole pipeline with 5 iterations and default
//! parameters; after the pipeline it prints the per-stage times of one run and the process's
//! peak resident memory (VmHWM).
//!
//! Run: `cargo bench -p murk --bench ps` (about 7 minutes on 2 cores: criterion's minimum of
//! 10 samples each); one case: `cargo bench -p murk --bench ps -- kernel_build_initial_plane`.

use criterion::{criterion_group, criterion_main, Criterion};

use murk::ps::bicgstab::{bicgstab_block, BicgstabParams, BlockOperator};
use murk::ps::integrate::{integrate_normals, IntegrationParams};
use murk::ps::physics::{
    FTable, FacetEmission, FarField, ForwardKernel, KernelLayout, SurfaceGeometry,
};
use murk::ps::pipeline::back_project;
use murk::ps::{photometric_stereo, PsParams};
use murk::simulate::ps::{simulate_ps, PsSimConfig};
use murk::Monitor;

const R: usize = 81;

struct Augmented<'a>(&'a ForwardKernel);

impl BlockOperator for Augmented<'_> {
    fn dim(&self) -> usize {
        self.0.dim()
    }
    fn apply_block(&self, xs: &[f64], ys: &mut [f64], k: usize) {
        self.0.apply_block(xs, ys, k);
    }
}

fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

fn bench(c: &mut Criterion) {
    let cfg = PsSimConfig::default();
    let sim = simulate_ps(&cfg, &Monitor::noop()).expect("simulate");
    let cap = &sim.capture;
    let (w, h) = cap.dims();
    let ft = FTable::global();
    // The kernel of the true shape (what later iterations see).
    let points = back_project(&cap.intrinsics, w, &sim.gt_depth_mm, &cap.mask);
    let geom = SurfaceGeometry {
        width: w,
        height: h,
        intrinsics: cap.intrinsics,
        points_mm: points,
        normals: sim.gt_normals.clone(),
        mask: cap.mask.clone(),
        emission: FacetEmission::default(),
    };
    let object_pixels = cap.mask.iter().filter(|&&b| b).count();
    let mut g = c.benchmark_group(format!("ps_{w}x{h}_r{R}_{object_pixels}px"));
    g.sample_size(10);
    let params = PsParams {
        initial_distance_mm: sim.initial_distance_mm,
        support_r: R,
        max_iterations: 5,
        tolerance: 0.0,
        ..PsParams::default()
    };
    let coarse = params.kernel_layout().expect("layout");
    let exact = KernelLayout::exact(R).expect("layout");
    let eps = FarField::ConstantEpsilon;
    g.bench_function("kernel_build_exact", |b| {
        b.iter(|| ForwardKernel::build_with(ft, &cap.medium, &geom, &exact, eps).expect("kernel"))
    });
    g.bench_function("kernel_build_far_cells_3", |b| {
        b.iter(|| ForwardKernel::build_with(ft, &cap.medium, &geom, &coarse, eps).expect("kernel"))
    });
    // Far cells plus the per-pixel far field (κ_p over the outside of the support), and the
    // default: far cells plus the outside summed on coarse blocks.
    let per_pixel = FarField::PerPixel;
    g.bench_function("kernel_build_far_cells_3_per_pixel_far_field", |b| {
        b.iter(|| {
            ForwardKernel::build_with(ft, &cap.medium, &geom, &coarse, per_pixel).expect("kernel")
        })
    });
    let blocks = FarField::Blocks;
    g.bench_function("kernel_build_far_cells_3_far_blocks", |b| {
        b.iter(|| {
            ForwardKernel::build_with(ft, &cap.medium, &geom, &coarse, blocks).expect("kernel")
        })
    });
    // Eq. 4.41's isotropic facet instead of the Lambertian one, default layout and far field.
    let isotropic = SurfaceGeometry {
        emission: FacetEmission::Isotropic,
        ..geom.clone()
    };
    g.bench_function("kernel_build_isotropic_facet", |b| {
        b.iter(|| {
            ForwardKernel::build_with(ft, &cap.medium, &isotropic, &coarse, params.far_field)
                .expect("kernel")
        })
    });
    // The first iteration's kernel: the object's mask on a fronto-parallel plane at the
    // starting distance.
    let plane_depth = vec![sim.initial_distance_mm as f32; w * h];
    let plane = SurfaceGeometry {
        points_mm: back_project(&cap.intrinsics, w, &plane_depth, &cap.mask),
        normals: vec![[0.0, 0.0, -1.0]; w * h],
        ..geom.clone()
    };
    g.bench_function("kernel_build_initial_plane", |b| {
        b.iter(|| {
            ForwardKernel::build_with(ft, &cap.medium, &plane, &coarse, params.far_field)
                .expect("kernel")
        })
    });
    drop((isotropic, plane));
    let kernel = ForwardKernel::build_with(ft, &cap.medium, &geom, &coarse, params.far_field)
        .expect("kernel");
    eprintln!(
        "kernel memory: far cells {:.0} MiB, of which {} far-field block entries",
        kernel.bytes() as f64 / (1 << 20) as f64,
        kernel.far_block_entries()
    );
    let masked: Vec<usize> = (0..w * h).filter(|&p| cap.mask[p]).collect();
    let dim = kernel.dim();
    let m = cap.lights.len();
    let mut rhs = vec![0.0f64; dim * m];
    for (i, img) in cap.images.iter().enumerate() {
        for (k, &p) in masked.iter().enumerate() {
            rhs[i * dim + k] = f64::from(img.data()[p] - cap.backgrounds[i].data()[p]);
        }
    }
    g.bench_function("bicgstab_8_lights", |b| {
        b.iter(|| {
            let mut x = rhs.clone();
            bicgstab_block(
                &Augmented(&kernel),
                &rhs,
                &mut x,
                m,
                &BicgstabParams::default(),
                &Monitor::noop(),
            )
            .expect("solve")
        })
    });
    drop(kernel);
    // Eq. 4.60–4.62 on the true normals: one sparse Cholesky solve over the object's pixels.
    g.bench_function("integrate_normals", |b| {
        b.iter(|| {
            integrate_normals(
                &cap.intrinsics,
                w,
                h,
                &sim.gt_normals,
                &cap.mask,
                &IntegrationParams::default(),
            )
            .expect("integrate")
        })
    });
    let mut last = None;
    g.bench_function("pipeline_5_iterations", |b| {
        b.iter(|| last = Some(photometric_stereo(cap, &params, &Monitor::noop()).expect("ps")))
    });
    g.finish();
    if let Some(out) = last {
        eprintln!(
            "one pipeline run: total {:.2} s, backscatter removal {:.3} s",
            out.total_s, out.backscatter_s
        );
        for s in &out.iterations {
            eprintln!(
                "  iteration {}: kernel {:.2} s ({:.0} MiB), BiCGStab {:.2} s ({:?} iterations), \
                 normals {:.3} s, integration {:.3} s, backscatter tail {:.3} s",
                s.iteration,
                s.kernel_s,
                s.kernel_bytes as f64 / (1 << 20) as f64,
                s.solve_s,
                s.solver_iterations,
                s.normals_s,
                s.integrate_s,
                s.tail_s
            );
        }
    }
    if let Some(mib) = peak_rss_mib() {
        eprintln!("peak resident memory of the bench process: {mib:.0} MiB");
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
