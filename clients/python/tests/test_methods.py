"""Every reconstruction method through the client against a real server, checked against the
simulator's ground truth (loose bounds: the point is that the client's conversions — planar
layout, units, the COLMAP principal point — are right, which a wrong one breaks by far)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import murk_client as mc
from murk_client import Client

from .conftest import read_meta


def test_tof_depth_beats_the_raw_range(client: Client, tof_scene: Path) -> None:
    frame = mc.load_tof_frame(tof_scene)
    assert frame.modulation_frequency_hz == 16e6 and frame.intrinsics is not None
    seen: list[mc.JobStatus] = []
    r = client.tof_depth(
        frame.amplitude,
        frame.phase,
        modulation_frequency_hz=frame.modulation_frequency_hz,
        intrinsics=frame.intrinsics,
        light_position_m=frame.light_position_m,
        progress=seen.append,
    )
    h, w = frame.amplitude.shape
    for name in ("range_m", "raw_range_m", "mask", "scatter_amplitude", "weight_phase", "corrected_phase"):
        assert getattr(r, name).shape == (h, w), name
        assert getattr(r, name).dtype == np.float32, name
    assert r.z_depth_m is not None and r.z_depth_m.shape == (h, w)
    gt = mc.read_image(tof_scene / "gt_range_m.exr")
    obj = mc.read_image(tof_scene / "gt_object_mask.png") > 0.5
    sel = obj & (r.mask > 0.5)
    assert sel.sum() > 0.5 * obj.sum()
    raw_err = float(np.median(np.abs(r.raw_range_m[sel] - gt[sel])))
    err = float(np.median(np.abs(r.range_m[sel] - gt[sel])))
    assert err < 0.5 * raw_err, (err, raw_err)
    # The reported range uncertainty covers most object pixels' errors (about 1 sigma).
    assert r.range_std_m is not None and r.range_std_m.shape == (h, w)
    assert np.all(np.isfinite(r.range_std_m)) and np.all(r.range_std_m > 0)
    assert float(np.mean(np.abs(r.range_m[sel] - gt[sel]) <= 3 * r.range_std_m[sel])) > 0.8
    # z-depth is range projected on the optical axis: never longer than the range.
    assert np.all(r.z_depth_m[sel] <= r.range_m[sel] + 1e-4)
    assert seen and seen[-1].state == mc.JobState.SUCCEEDED and seen[-1].method == "tof_depth"
    assert r.job_id == seen[-1].id


def test_tof_points_are_the_measured_pixels(client: Client, tof_scene: Path) -> None:
    frame = mc.load_tof_frame(tof_scene)
    k = frame.intrinsics
    assert k is not None
    r = client.tof_depth(
        frame.amplitude,
        frame.phase,
        modulation_frequency_hz=frame.modulation_frequency_hz,
        intrinsics=k,
        light_position_m=frame.light_position_m,
        return_points=True,
    )
    assert r.points is not None and r.colors is not None and r.range_std_m is not None
    assert r.z_depth_m is not None
    measured = r.range_std_m < 0.1
    assert len(r.points) == int(measured.sum()) and r.colors.shape == r.points.shape
    # Each point lies on its pixel's ray at the pixel's z-depth (row-major order).
    v, u = np.nonzero(measured)
    z = r.z_depth_m[measured]
    np.testing.assert_allclose(r.points[:, 2], z, rtol=1e-6)
    np.testing.assert_allclose(r.points[:, 0], (u - k.cx) / k.fx * z, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(r.points[:, 1], (v - k.cy) / k.fy * z, rtol=1e-4, atol=1e-5)
    with pytest.raises(mc.ClientInputError) as e:
        client.tof_depth(
            frame.amplitude,
            frame.phase,
            modulation_frequency_hz=frame.modulation_frequency_hz,
            return_points=True,
        )
    assert e.value.field == "request.tof_depth.return_points"


def test_mvs_depth_with_colmap_model(client: Client, mvs_scene: Path) -> None:
    meta = read_meta(mvs_scene)
    model = mc.load_colmap_model(mvs_scene / "sparse")
    ref = meta["reference"]
    sources = model.nearest_sources(ref, 4)
    assert len(sources) == 4 and ref not in sources
    z = (
        model.points_scene_units @ model.image(ref).pose.rotation.T
        + model.image(ref).pose.translation_scene_units
    )
    zs = z[:, 2][z[:, 2] > 0]
    kwargs = dict(
        near_scene_units=0.75 * float(zs.min()), far_scene_units=1.5 * float(zs.max()), num_planes=64
    )
    views = [model.view(n, mvs_scene / "images") for n in sources]
    reference = model.view(ref, mvs_scene / "images")
    r = client.mvs_depth(
        reference, views, airlight=meta["airlight"], beta_per_scene_unit=meta["beta"], **kwargs
    )
    gt = mc.read_image(mvs_scene / "depth" / ref.replace(".png", ".exr"))
    assert r.z_depth.shape == gt.shape == reference.image.shape[:2]  # type: ignore[union-attr]
    assert r.cost_volume == "dehazing" and r.num_planes == 64
    # The simulator's lenses do not vignette.
    assert r.vignetting_falloff == 0.0
    assert len(r.source_falloffs) == len(views) and all(d == 0.0 for d in r.source_falloffs)
    valid = gt > 0
    l1_rel = float(np.mean(np.abs(r.z_depth[valid] - gt[valid]) / gt[valid]))
    assert l1_rel < 0.15, l1_rel
    # The ordinary volume runs without A and β.
    o = client.mvs_depth(reference, views, cost_volume="ordinary", **kwargs)
    assert o.cost_volume == "ordinary" and o.job_id != r.job_id


def test_rectified_stereo_from_the_rig(client: Client, mvs_scene_rectified: Path) -> None:
    meta = read_meta(mvs_scene_rectified)
    model = mc.load_colmap_model(mvs_scene_rectified / "sparse")
    left = model.view("view_00.png", mvs_scene_rectified / "images")
    right = model.view("view_01.png", mvs_scene_rectified / "images")
    # The rig as a camera driver gives it: the left intrinsics and the right camera's offset.
    baseline = -float(right.pose.translation_scene_units[0])
    r = client.rectified_stereo(
        left.image,
        right.image,
        intrinsics=left.intrinsics,
        baseline=baseline,
        depth_range=(1.5, 15.0),
        airlight=meta["airlight"],
        beta=meta["beta"],
        return_points=True,
    )
    gt = mc.read_image(mvs_scene_rectified / "depth" / "view_00.exr")
    assert r.z_depth.shape == r.disparity.shape == gt.shape
    assert r.cost_volume == "dehazing" and r.num_planes > 2
    fx = left.intrinsics.fx  # type: ignore[union-attr]
    np.testing.assert_allclose(r.disparity, fx * baseline / r.z_depth, rtol=1e-4)
    valid = gt > 0
    cp = float(np.mean(np.abs(r.z_depth[valid] - gt[valid]) / gt[valid] < 0.1))
    assert cp > 0.5, cp
    assert r.points is not None and r.colors is not None
    assert r.points.shape == (int(np.sum(r.confidence > 0)), 3) and r.colors.shape == r.points.shape
    assert np.all(r.points[:, 2] > 0)
    # The ordinary volume without A and β; a bad rig names its field before anything is sent.
    o = client.rectified_stereo(left.image, right.image, intrinsics=left.intrinsics, baseline=baseline)
    assert o.cost_volume == "ordinary" and o.points is None
    with pytest.raises(mc.ClientInputError) as e:
        client.rectified_stereo(left.image, right.image, intrinsics=left.intrinsics, baseline=0.0)
    assert e.value.field == "request.rectified_stereo.baseline"
    with pytest.raises(mc.InvalidArgument) as bad:
        client.rectified_stereo(
            left.image, right.image, intrinsics=left.intrinsics, baseline=baseline, disparity_range_px=(5, 3)
        )
    assert bad.value.field == "request.rectified_stereo.max_disparity_px"


def params_of(client: Client, scene: Path) -> mc.ScatteringParamsResult:
    meta = read_meta(scene)
    model = mc.load_colmap_model(scene / "sparse")
    ref = meta["reference"]
    return client.scattering_params(
        model.view(ref, scene / "images"),
        [model.view(n, scene / "images") for n in model.nearest_sources(ref, 4)],
        model.points_scene_units,
        airlight_source="dark_channel",
        options={"num_planes": 64, "search_planes": 32},
    )


def test_scattering_params_says_when_beta_is_not_determined(
    client: Client, mvs_scene_rectified: Path
) -> None:
    # A rectified pair: the points' depths do not differ between the views.
    r = params_of(client, mvs_scene_rectified)
    assert not r.identifiable and r.identifiability == "no_depth_difference"
    # The best estimate is still returned (the joint fit when it converged), marked as a guess.
    assert r.beta_source in ("joint_fit", "sweep") and r.beta_per_scene_unit > 0


def test_scattering_params_recovers_a_and_beta(client: Client, mvs_scene_forward: Path) -> None:
    meta = read_meta(mvs_scene_forward)
    r = params_of(client, mvs_scene_forward)
    assert abs(r.airlight - meta["airlight"]) < 0.03, (r.airlight, meta["airlight"])
    assert r.beta_per_scene_unit > 0 and r.grid and r.num_sparse_points >= 10
    assert r.airlight_source == "dark_channel"
    # What is known is said: the points determine A and β here, with standard errors, and the
    # truth lies within a few of them; the range came from the points and did not bind.
    assert r.identifiable and r.identifiability == "identifiable" and r.beta_source == "joint_fit"
    assert r.airlight_std_error is not None and r.beta_std_error_per_scene_unit is not None
    assert abs(r.beta_per_scene_unit - meta["beta"]) < 4 * r.beta_std_error_per_scene_unit + 0.01
    assert r.beta_range_from_points and r.beta_bound is None
    # The points' A agrees with the dark channel's A0 within its typical error: no conflict.
    assert r.airlight_conflict is None and r.warnings == ()
    assert len(r.source_gains) == 4 and all(abs(g - 1) < 0.05 for g in r.source_gains)
    assert r.depth.z_depth.shape == (72, 96) and r.depth.num_planes == 64


def test_scattering_params_with_observations_reports_the_poses_share(
    client: Client, mvs_scene_forward: Path
) -> None:
    meta = read_meta(mvs_scene_forward)
    model = mc.load_colmap_model(mvs_scene_forward / "sparse")
    ref = meta["reference"]
    views = [model.view(n, mvs_scene_forward / "images") for n in [ref, *model.nearest_sources(ref, 4)]]
    # Where each view sees each point, 0.5 px of noise added: observations as SfM would give.
    rng = np.random.default_rng(3)
    obs = []
    for i, p in enumerate(np.asarray(model.points_scene_units)):
        for v, view in enumerate(views):
            x, y, z = view.pose.rotation @ p + view.pose.translation_scene_units
            k = view.intrinsics
            if z > 0:
                u, w = k.fx * x / z + k.cx, k.fy * y / z + k.cy
                obs.append([i, v, u + 0.5 * rng.standard_normal(), w + 0.5 * rng.standard_normal()])
    r = client.scattering_params(
        views[0],
        views[1:],
        model.points_scene_units,
        airlight_source="dark_channel",
        observations=obs,
        options={"num_planes": 64, "search_planes": 32},
    )
    plain = params_of(client, mvs_scene_forward)
    assert (r.airlight, r.beta_per_scene_unit) == (plain.airlight, plain.beta_per_scene_unit)
    pe = r.pose_error
    assert pe is not None and pe.undetermined == "" and pe.points > 60
    assert 0.4 < pe.reprojection_rms_px < 0.7, pe
    assert pe.beta_std_error_per_scene_unit is not None and pe.beta_std_error_per_scene_unit > 0
    assert r.beta_std_error_per_scene_unit is not None and plain.beta_std_error_per_scene_unit is not None
    assert r.beta_std_error_per_scene_unit > plain.beta_std_error_per_scene_unit
    assert plain.pose_error is None
    # Where SfM put its points counts with or without observations: the same share in both.
    for res in (r, plain):
        sh = res.sampling
        assert sh is not None and sh.wide_blur_px == 2 * sh.base_blur_px, sh
        assert sh.beta_std_error_per_scene_unit is not None and sh.refit_beta_per_scene_unit is not None
        # β* travels as a float32; the share is the f64 fit's move.
        moved = abs(sh.refit_beta_per_scene_unit - res.beta_per_scene_unit)
        assert sh.beta_std_error_per_scene_unit == pytest.approx(moved, abs=1e-6), sh
    assert r.sampling == plain.sampling
    # The model's own observations (the simulator's: exact projections of the true points).
    own = model.observations(ref, model.nearest_sources(ref, 4))
    assert own.shape[1] == 4 and len(own) > 2 * len(model.points_scene_units)
    r = client.scattering_params(
        views[0],
        views[1:],
        model.points_scene_units,
        airlight_source="dark_channel",
        observations=own,
        options={"num_planes": 64, "search_planes": 32},
    )
    assert r.pose_error is not None and r.pose_error.points > 60, r.pose_error


def test_scattering_params_reports_an_airlight_conflict(client: Client, mvs_scene_forward: Path) -> None:
    meta = read_meta(mvs_scene_forward)
    model = mc.load_colmap_model(mvs_scene_forward / "sparse")
    ref = meta["reference"]
    # A0 given 0.3 away from the truth, far beyond its stated error (the prior's default scale):
    # the points still place A, and the result says the two disagree.
    a0 = meta["airlight"] - 0.3
    r = client.scattering_params(
        model.view(ref, mvs_scene_forward / "images"),
        [model.view(n, mvs_scene_forward / "images") for n in model.nearest_sources(ref, 4)],
        model.points_scene_units,
        airlight_source="given",
        airlight=a0,
        options={"num_planes": 64, "search_planes": 32},
    )
    c = r.airlight_conflict
    assert isinstance(c, mc.AirlightConflict), r.airlight_conflict
    assert abs(c.airlight_initial - a0) < 1e-6 and c.sigmas > 3
    assert abs(c.fitted_airlight - meta["airlight"]) < 0.05
    assert not r.identifiable and len(r.warnings) == 1 and "SfM model" in r.warnings[0]


def test_photometric_stereo_normals(client: Client, ps_scene: Path) -> None:
    cap = mc.load_ps_capture(ps_scene)
    assert len(cap.lights) == 8 and cap.initial_distance_mm is not None
    r = client.photometric_stereo(
        cap.lights,
        cap.mask,
        intrinsics=cap.intrinsics,
        beta_per_mm=cap.beta_per_mm,
        sigma_per_mm=cap.sigma_per_mm,
        initial_distance_mm=cap.initial_distance_mm,
        options={"support_r": 21, "max_iterations": 2, "return_iteration_normals": True},
    )
    assert r.normals.shape == (48, 48, 3) and r.depth_mm.shape == (48, 48)
    assert len(r.iteration_normals) == len(r.iterations) >= 1
    obj = cap.mask > 0.5
    assert cap.gt_normals is not None
    cos = np.clip(np.sum(r.normals[obj] * cap.gt_normals[obj], axis=1), -1.0, 1.0)
    mean_err_deg = float(np.degrees(np.arccos(cos)).mean())
    assert mean_err_deg < 10.0, mean_err_deg
    # Off the object: depth NaN, normal (0, 0, -1).
    assert np.isnan(r.depth_mm[~obj]).all()
    # Depth in mm around the initial plane.
    assert abs(float(np.nanmean(r.depth_mm)) - cap.initial_distance_mm) < 0.2 * cap.initial_distance_mm


def test_photometric_stereo_finds_the_distance(client: Client, ps_scene: Path) -> None:
    """No distance given: the server searches for it and fits it to the lights' fall-off."""
    cap = mc.load_ps_capture(ps_scene)
    assert cap.gt_depth_mm is not None
    obj = cap.mask > 0.5
    truth = float(cap.gt_depth_mm[obj].mean())
    r = client.photometric_stereo(
        cap.lights,
        cap.mask,
        intrinsics=cap.intrinsics,
        beta_per_mm=cap.beta_per_mm,
        sigma_per_mm=cap.sigma_per_mm,
        initial_distance_mm=None,
        options={"support_r": 21, "max_iterations": 4},
    )
    assert r.proto.HasField("initial_distance_fit")
    assert all(it.HasField("distance_fit") for it in r.iterations)
    assert abs(r.mean_depth_mm / truth - 1) < 0.05, (r.mean_depth_mm, truth)
    with pytest.raises(mc.ClientInputError) as e:
        mc.photometric_stereo_request(
            cap.lights,
            cap.mask,
            intrinsics=cap.intrinsics,
            beta_per_mm=cap.beta_per_mm,
            sigma_per_mm=cap.sigma_per_mm,
            fix_distance=True,
        )
    assert e.value.field == "request.photometric_stereo.initial_distance_mm"
