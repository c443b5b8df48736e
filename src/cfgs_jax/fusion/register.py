"""Registration of a date into the reference frame (paper §"Multi-Temporal Gaussian Fusion", step 1).

``transform_gaussians`` applies a Sim(3) to a date's splats; ``register_date`` finds that Sim(3)
from the images with pycolmap and optimistix.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from scipy.spatial.transform import Rotation

from cfgs_jax.errors import InputError
from cfgs_jax.fusion.config import RegisterConfig
from cfgs_jax.io.colmap import Scene
from cfgs_jax.io.images import write_image
from cfgs_jax.io.run_dir import camera_in_frame
from cfgs_jax.model import Gaussians
from cfgs_jax.sim3 import Sim3, matrix_to_quat, quat_multiply
from cfgs_jax.splat.sh import rotate


def transform_gaussians(g: Gaussians, sim3: Sim3) -> Gaussians:
    """The splats of ``g`` moved by x ↦ s·R·x + t: means s·R·μ + t, quaternions q_R ⊗ q (Σ ↦ s²·R·Σ·Rᵀ),
    log-scales + log s, the view-dependent colour turned with them (``splat.sh.rotate``: seen along R·d
    as before along d); opacity and DC colour unchanged. Float64 transform, result in ``g``'s dtype."""
    dtype = jnp.result_type(g.means)
    means = sim3.apply(np.asarray(g.means, np.float64))
    q_r = jnp.asarray(matrix_to_quat(sim3.rotation), jnp.float64 if dtype == jnp.float64 else jnp.float32)
    quats = quat_multiply(q_r, jnp.asarray(g.quats, q_r.dtype))
    return Gaussians(
        jnp.asarray(means, dtype),
        jnp.asarray(quats, dtype),
        jnp.asarray(g.log_scales, dtype) + jnp.asarray(np.log(sim3.scale), dtype),
        g.opacity_logits,
        g.colors,
        None if g.sh_rest is None else jnp.asarray(rotate(g.sh_rest, sim3.rotation), dtype),
    )


# ------------------------------------------------------------------------------------ SfM registration


@dataclasses.dataclass(frozen=True)
class Registration:
    """``transform``: date frame → reference frame. Residuals are RMS camera-centre misfits after the
    fit, as a fraction of the reference cameras' extent, and RMS orientation misfits in degrees.
    ``posed_on_persistent``: the date's images were posed on the structure at least two registered
    dates see (``RegisterConfig.persistent_structure``), not taken from the joint SfM."""

    transform: Sim3
    registered_reference: int
    registered_date: int
    centre_residual: float
    rotation_residual_deg: float
    posed_on_persistent: bool = False

    def to_dict(self) -> dict:
        return {
            "transform": self.transform.to_dict(),
            "registered_reference": self.registered_reference,
            "registered_date": self.registered_date,
            "centre_residual_rel": self.centre_residual,
            "rotation_residual_deg": self.rotation_residual_deg,
            "posed_on_persistent": self.posed_on_persistent,
        }


def _evenly(n: int, k: int) -> list[int]:
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(n, k))})


def _matrix4(rigid) -> np.ndarray:
    """A pycolmap ``Rigid3d`` as a 4×4 homogeneous matrix."""
    return np.vstack([np.asarray(rigid.matrix(), np.float64), [0.0, 0.0, 0.0, 1.0]])


def _world_from_cam(cam_from_world) -> np.ndarray:
    return np.linalg.inv(np.asarray(cam_from_world, np.float64))


def _rotvec_to_matrix(v):
    """Rodrigues' formula (jnp, differentiable at 0 through the series guard)."""
    theta2 = jnp.sum(v * v)
    theta = jnp.sqrt(jnp.maximum(theta2, 1e-30))
    k = jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], v.dtype)
    small = theta2 < 1e-12
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / jnp.maximum(theta2, 1e-30))
    return jnp.eye(3, dtype=v.dtype) + a * k + b * jnp.matmul(k, k, precision=jax.lax.Precision.HIGHEST)


def refine_sim3_pair(init_a: Sim3, init_b: Sim3, ref_pairs, date_pairs, extent: float, max_steps: int = 200):
    """Joint Levenberg–Marquardt (optimistix) refinement of A: SfM frame → reference and
    B: date frame → reference from the registered cameras.

    ``ref_pairs`` = (centres, rotations) of reference images in the SfM frame and in the reference
    frame; ``date_pairs`` = the same for the date's images in the SfM frame and in the date frame.
    Residuals: A(c_sfm) − c_ref and A(c_sfm) − B(c_date) over ``extent``; R_A·R_sfm − R_ref and
    R_A·R_sfm − R_B·R_date (world-from-camera rotations). Returns (A, B, converged): the two Sim3 and
    whether optimistix reported success with finite parameters within ``max_steps``."""

    (c_rs, r_rs), (c_rr, r_rr) = ref_pairs
    (c_ds, r_ds), (c_dd, r_dd) = date_pairs

    def unpack(y):
        return y[0], _rotvec_to_matrix(y[1:4]), y[4:7]

    def residuals(y, args):
        c_rs, r_rs, c_rr, r_rr, c_ds, r_ds, c_dd, r_dd = args
        la, ra, ta = unpack(y[:7])
        lb, rb, tb = unpack(y[7:])
        mul = functools.partial(jnp.matmul, precision=jax.lax.Precision.HIGHEST)
        rotate = lambda r, rs: jnp.einsum("ij,njk->nik", r, rs, precision=jax.lax.Precision.HIGHEST)
        a_c = lambda c: jnp.exp(la) * mul(c, ra.T) + ta
        out = [
            ((a_c(c_rs) - c_rr) / extent).ravel(),
            ((a_c(c_ds) - (jnp.exp(lb) * mul(c_dd, rb.T) + tb)) / extent).ravel(),
            (rotate(ra, r_rs) - r_rr).ravel(),
            (rotate(ra, r_ds) - rotate(rb, r_dd)).ravel(),
        ]
        return jnp.concatenate(out)

    def pack(s: Sim3):

        return np.concatenate([[np.log(s.scale)], Rotation.from_matrix(s.rotation).as_rotvec(), s.translation])

    @jax.jit
    def solve(y0, args):
        sol = optx.least_squares(
            residuals,
            optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12),
            y0,
            args=args,
            max_steps=max_steps,
            throw=False,
        )
        return sol.value, sol.result == optx.RESULTS.successful

    with jax.enable_x64(True):
        data = tuple(jnp.asarray(x, jnp.float64) for x in (c_rs, r_rs, c_rr, r_rr, c_ds, r_ds, c_dd, r_dd))
        y, ok = solve(jnp.asarray(np.concatenate([pack(init_a), pack(init_b)]), jnp.float64), data)
        y = np.asarray(y, np.float64)
        ok = bool(ok) and bool(np.all(np.isfinite(y)))

    def to_sim3(p):
        return Sim3(float(np.exp(p[0])), np.asarray(_rotvec_to_matrix(jnp.asarray(p[1:4])), np.float64), p[4:7].copy())

    return to_sim3(y[:7]), to_sim3(y[7:]), ok


def _sim3_from_pycolmap(s) -> Sim3:
    m = np.asarray(s.matrix(), np.float64)  # [3, 4] = [s·R | t]
    scale = float(np.cbrt(np.linalg.det(m[:, :3])))
    return Sim3(scale, m[:, :3] / scale, m[:, 3].copy())


def _joint_sfm(anchors, date, config: RegisterConfig, workdir) -> tuple:
    """One pycolmap SfM (SIFT, exhaustive matching, incremental mapping with the dates' pinhole
    intrinsics fixed) of ``images_per_date`` evenly spaced images of each registered date (``anchors``)
    and of ``date``. Returns the largest reconstruction and {SfM image name: (tag, image index)}, tag
    "ref<j>" for anchor j and "new" for the date."""

    import pycolmap

    sides = [(f"ref{j}", scene) for j, (scene, _) in enumerate(anchors)] + [("new", date)]
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        tmp = Path(tmp)
        picked = {}
        for tag, scene in sides:
            (tmp / "images" / tag).mkdir(parents=True)
            for i in _evenly(len(scene), config.images_per_date):
                name = f"{tag}/{i:05d}.png"
                write_image(tmp / "images" / name, scene.load_image(i))  # RGB, at the cameras' size
                picked[name] = (tag, i)
        db = tmp / "database.db"
        for tag, scene in sides:
            cam = scene.cameras[0]
            reader = pycolmap.ImageReaderOptions(
                camera_model="PINHOLE", camera_params=",".join(str(float(x)) for x in (cam.fx, cam.fy, cam.cx, cam.cy))
            )
            extraction = pycolmap.FeatureExtractionOptions()
            extraction.sift.peak_threshold = config.sift_peak_threshold
            pycolmap.extract_features(
                db,
                tmp / "images",
                image_names=[n for n, (t, _) in picked.items() if t == tag],
                camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
            )
        pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
        opts = pycolmap.IncrementalPipelineOptions(
            random_seed=config.seed,
            ba_refine_focal_length=False,
            ba_refine_principal_point=False,
            ba_refine_extra_params=False,
            min_num_matches=config.min_num_matches,
        )
        opts.mapper.init_min_num_inliers = config.init_min_num_inliers
        opts.mapper.abs_pose_min_num_inliers = config.abs_pose_min_num_inliers
        opts.mapper.init_min_tri_angle = config.init_min_tri_angle
        maps = pycolmap.incremental_mapping(db, tmp / "images", tmp / "sfm", options=opts)
    if not maps:
        raise InputError(
            "joint SfM of the date and the registered dates found no reconstruction",
            path=date.root,
            field="images",
            fix="the dates share too little; pass known transforms with --transforms JSON",
        )
    return max(maps.values(), key=lambda r: r.num_reg_images()), picked


def persistent_observations(tracks: dict, date_images: list, min_dates: int = 2) -> dict:
    """{image: [(keypoint index, point id)]} of the ``date_images`` keeping only the points whose
    track holds images of at least ``min_dates`` distinct registered dates. ``tracks``: {point id:
    set of the tags ("ref<j>" for registered date j, "new" for the date) of the images that see it};
    ``date_images``: (image, [(keypoint index, point id)]) pairs. A point the registered dates agree on
    persisted between their captures; one that only a single registered date sees may lie on a surface
    that has changed since, which would drag the date towards that date's state."""
    keep = {pid for pid, tags in tracks.items() if len({t for t in tags if t.startswith("ref")}) >= min_dates}
    return {image: [(k, pid) for k, pid in obs if pid in keep] for image, obs in date_images}


def _pose_on_persistent_structure(rec, picked: dict, config: RegisterConfig) -> dict | None:
    """The date's images posed against the structure at least two registered dates see, that
    structure bundle-adjusted from the registered dates' images alone: {SfM image name: cam_from_world
    4×4} of those and of the registered dates' images in the adjusted frame; None when fewer than
    ``min_registered`` of the date's images pose, or fewer than two dates are registered (the joint
    SfM's own poses then stand)."""
    import pycolmap

    tag_of = {i: picked[img.name][0] for i, img in rec.images.items() if img.name in picked}
    if len({t for t in tag_of.values() if t != "new"}) < 2:
        return None
    tracks = {pid: {tag_of.get(e.image_id, "") for e in p.track.elements} for pid, p in rec.points3D.items()}
    date_images = [
        (i, [(k, p.point3D_id) for k, p in enumerate(img.points2D) if p.has_point3D()])
        for i, img in rec.images.items()
        if tag_of.get(i) == "new" and img.has_pose
    ]
    observations = persistent_observations(tracks, date_images)
    anchored = pycolmap.Reconstruction(rec)
    for i, _ in date_images:
        anchored.deregister_frame(anchored.images[i].frame_id)
    adjust = pycolmap.BundleAdjustmentOptions()
    adjust.print_summary = False
    adjust.refine_focal_length = adjust.refine_principal_point = adjust.refine_extra_params = False  # as the mapper
    pycolmap.bundle_adjustment(anchored, adjust)
    pnp = pycolmap.AbsolutePoseEstimationOptions()
    pnp.ransac.random_seed = config.seed
    poses = {}
    for i, obs in observations.items():
        obs = [(k, pid) for k, pid in obs if anchored.exists_point3D(pid)]
        if len(obs) < config.abs_pose_min_num_inliers:
            continue
        img = rec.images[i]
        got = pycolmap.estimate_and_refine_absolute_pose(
            np.array([img.points2D[k].xy for k, _ in obs], np.float64),
            np.array([anchored.points3D[pid].xyz for _, pid in obs], np.float64),
            rec.cameras[img.camera_id],
            pnp,
        )
        if got is not None and got["num_inliers"] >= config.abs_pose_min_num_inliers:
            poses[img.name] = _matrix4(got["cam_from_world"])
    if len(poses) < config.min_registered:
        return None
    for img in anchored.images.values():  # the registered dates' images, in the same adjusted frame
        if img.has_pose and img.name in picked:
            poses[img.name] = _matrix4(img.cam_from_world())
    return poses


def _registered_poses(rec, picked: dict, anchors, date, config: RegisterConfig, poses=None) -> tuple[list, list]:
    """For the registered images of the registered dates (their cameras posed in the reference frame)
    and of ``date``: [SfM centres, SfM rotations, own centres, own rotations] (world-from-camera), the
    registered dates' then the date's; too few registered is an error. ``poses``: {image name:
    cam_from_world} replacing the SfM's poses (only those images then count)."""
    pairs = {"ref": ([], [], [], []), "new": ([], [], [], [])}
    for img in rec.images.values():
        if not img.has_pose or img.name not in picked:
            continue
        tag, i = picked[img.name]
        if poses is not None and img.name not in poses:
            continue
        if tag == "new":
            camera = date.cameras[i]
        else:
            scene, sim = anchors[int(tag[3:])]
            camera = camera_in_frame(scene.cameras[i], sim)
        key = "new" if tag == "new" else "ref"
        w_sfm = _world_from_cam(_matrix4(img.cam_from_world()) if poses is None else poses[img.name])
        w_own = _world_from_cam(camera.cam_from_world)
        for lst, v in zip(pairs[key], (w_sfm[:3, 3], w_sfm[:3, :3], w_own[:3, 3], w_own[:3, :3])):
            lst.append(v)
    n_ref, n_new = len(pairs["ref"][0]), len(pairs["new"][0])
    if min(n_ref, n_new) < config.min_registered:
        raise InputError(
            f"only {n_new} of {len([t for t, _ in picked.values() if t == 'new'])} images of this date and "
            f"{n_ref} images of the registered dates registered in the joint SfM (need ≥ {config.min_registered} "
            "each)",
            path=date.root,
            field="images",
            fix=f"put more images of each date into the joint SfM ([register] images_per_date, now "
            f"{config.images_per_date}: e.g. --set register.images_per_date={2 * config.images_per_date}), "
            "or pass known transforms with --transforms JSON",
        )
    return [np.asarray(x) for x in pairs["ref"]], [np.asarray(x) for x in pairs["new"]]


def _robust_start(ref, new, date, config: RegisterConfig, extent: float) -> tuple[Sim3, Sim3]:
    """Closed-form robust Sim(3)s on camera centres (pycolmap ``estimate_sim3d_robust``, inlier
    threshold 5 % of the extent): SfM → reference, and date → reference through the SfM."""
    import pycolmap

    ransac = pycolmap.RANSACOptions(random_seed=config.seed)
    ransac.max_error = 0.05 * extent
    a0 = pycolmap.estimate_sim3d_robust(ref[0], ref[2], ransac)  # SfM → reference
    b_sfm = pycolmap.estimate_sim3d_robust(new[0], new[2], ransac)  # SfM → date
    if a0 is None or b_sfm is None:
        raise InputError(
            "no consistent Sim(3) between the SfM and the dates' cameras",
            path=date.root,
            fix="check the dates' COLMAP poses, or pass --transforms JSON",
        )
    a0, b_sfm = (
        _sim3_from_pycolmap(a0["tgt_from_src"] if isinstance(a0, dict) else a0),
        _sim3_from_pycolmap(b_sfm["tgt_from_src"] if isinstance(b_sfm, dict) else b_sfm),
    )
    return a0, a0.compose(b_sfm.inverse())


def register_date(
    reference, date, *, config: RegisterConfig | None = None, workdir=None, progress=None
) -> Registration:
    """The Sim(3) that brings ``date`` (a ``Scene``) into the reference frame.

    ``reference``: the reference date's ``Scene``, or every date registered so far as (``Scene``, its
    Sim(3) into the reference frame) pairs, the reference date first: the images of the whole fused
    model, as the paper registers a new date into the SfM model of all of them, so a date that shares
    views only with a later date still joins. A subset of every date's images goes through one joint
    SfM (pycolmap: SIFT, exhaustive matching, incremental mapping with the dates' own pinhole intrinsics
    held fixed). The registered dates' images tie the SfM frame to the reference frame (their cameras
    posed there) and the date's images tie it to the date's frame, both through the camera poses the
    datasets already have: a robust closed-form Sim(3)
    (pycolmap ``estimate_sim3d_robust`` on camera centres) initialises a joint optimistix
    Levenberg–Marquardt over centres and orientations. With two or more dates registered, the date's
    images are first posed again against the points at least two of them see, bundle-adjusted without
    the date (``persistent_structure``): features on a surface that changed after one registered date
    (risen water) match across dates and would otherwise drag the date's cameras. Fewer than
    ``min_registered`` images of either date registered, or a fit that does not converge, is an error
    naming the date."""
    import pycolmap

    config = config or RegisterConfig()
    if not logging.getLogger("cfgs_jax").isEnabledFor(logging.INFO):
        pycolmap.logging.minloglevel = 2  # COLMAP's per-image INFO lines only with --verbose
    anchors = [(reference, Sim3.identity())] if isinstance(reference, Scene) else list(reference)
    rec, picked = _joint_sfm(anchors, date, config, workdir)
    poses = _pose_on_persistent_structure(rec, picked, config) if config.persistent_structure else None
    ref, new = _registered_poses(rec, picked, anchors, date, config, poses)
    n_ref, n_new = len(ref[0]), len(new[0])
    centres = np.stack(
        [np.asarray(camera_in_frame(c, anchors[0][1]).center, np.float64) for c in anchors[0][0].cameras]
    )
    extent = centre_extent(centres)
    a0, b0 = _robust_start(ref, new, date, config, extent)
    a, b, converged = refine_sim3_pair(
        a0, b0, ((ref[0], ref[1]), (ref[2], ref[3])), ((new[0], new[1]), (new[2], new[3])), extent, config.lm_max_steps
    )
    if not converged:
        raise InputError(
            f"registering this date to the reference failed: the joint Levenberg–Marquardt fit of the Sim(3) "
            f"(optimistix) did not converge within {config.lm_max_steps} steps ({n_ref} reference and {n_new} "
            f"date images registered)",
            path=date.root,
            field="register.lm_max_steps",
            fix="raise [register] lm_max_steps, check the date's COLMAP poses, or pass --transforms JSON",
        )
    c_err = np.concatenate([a.apply(ref[0]) - ref[2], a.apply(new[0]) - b.apply(new[2])])
    r_err = [np.degrees(rotation_angle(a.rotation @ r1, r2)) for r1, r2 in zip(ref[1], ref[3])]
    r_err += [np.degrees(rotation_angle(a.rotation @ r1, b.rotation @ r2)) for r1, r2 in zip(new[1], new[3])]
    rms_centre = float(np.sqrt(np.mean(np.sum(c_err**2, axis=1))) / extent)
    return Registration(b, n_ref, n_new, rms_centre, float(np.sqrt(np.mean(np.square(r_err)))), poses is not None)


def rotation_angle(r1, r2) -> float:
    """The angle of the rotation R = R₁R₂ᵀ in radians, atan2(|v|, tr R − 1) with v the axis vector
    (R₃₂ − R₂₃, R₁₃ − R₃₁, R₂₁ − R₁₂) = 2 sin θ · axis: the arccos of (tr R − 1) / 2 without its loss
    of precision near 0 (where the arccos of a float64 cosine cannot resolve angles below ~1e-8 rad)."""
    r = np.asarray(r1, np.float64) @ np.asarray(r2, np.float64).T
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return float(np.arctan2(np.linalg.norm(v), np.trace(r) - 1.0))


def centre_extent(centres) -> float:
    """The largest distance of camera centres from their mean: the scale registration residuals and
    errors are measured in."""
    c = np.asarray(centres, np.float64)
    return float(np.max(np.linalg.norm(c - c.mean(0), axis=1)))
