"""Track a simulated drive with the histogram filter (:mod:`enmi_torch.tracking`) against per-frame argmax.

The map: scikit-image's CC0 textures and photographs tiled along a road, 320 cells wide and 2560 long (2.5 cm cells:
8 m x 64 m): ``gravel``, ``grass``, ``brick`` (repetitive), ``camera`` and ``moon``, with painted edge lines, a
dashed centre line and stop bars. The vehicle drives up the road (rows decreasing) at about 9 cells (22 cm) per
frame, weaving (yaw within about +-6 degrees). Each frame is rendered through the paper's road camera
(:meth:`~enmi_torch.RoadCamera.paper`, 120 x 160 pixels): the road under the pose is warped into the camera with
:func:`~enmi_torch.unrectify`, Gaussian pixel noise is added, and the image is rectified back with kornia
(:func:`~enmi_torch.rectify`, 4 x 4 samples per cell) onto a 64 x 64 grid of 2.5 cm cells 40 cm to 200 cm ahead.
The analytic variance of a cell is ``N0 / A`` (``A`` the pixels it covers, :func:`homography_variance`); the learned
variance is the empirical variance of held-out renders against their noiseless rendering; the uniform control is one
variance, the learned map's mean.

Hard stretches: strong noise (frames 150-179, pixel noise x 4), a changed appearance (frames 60-89: the ground seen
through a non-monotonic response ``255 |2 v / 255 - 1|^0.8``, as when the map was made by another sensor) and the
repetitive ``brick`` tile. Odometry (``du``, ``dv``, ``dyaw`` in the frame's axes) has a 3 % scale error, a yaw-rate
bias of 0.05 degrees per frame and white noise.

The filter runs as README shows it, without calibration (each frame's temperature is
:func:`enmi_torch.tracking.calibration.grid_temperature`); the odometry noise is the RMS of the increment errors of
a held-out odometry sequence. ``--calibrate`` fits each score's temperature and peak z-score threshold on held-out
frames instead (:func:`enmi_torch.tracking.calibrate_temperature`), written as ``calibration_<method>.json`` under
``--logdir`` (``runs/drive``), with the TensorBoard logs of the errors
(``tensorboard --logdir runs/drive/tensorboard``).
``--scene-change S`` renders the frames from the road changed since the map was made (every change of
:mod:`enmi_torch.data.scene_change` at strength ``S``, the map unchanged); ``--noise-scale`` multiplies the pixel
noise; ``--seeds`` runs one drive per seed and prints the mean and standard error across them, and each row less the
first, paired drive by drive. ECR runs as each of ``--variants`` (:mod:`~data_tools.experiments.drive.variants`: the
tracker's default ``binned``, ``ECR(response="binned", misfit="correlated")`` per frame; ``held``, ``ECR()`` with its
noise model held from a frame it trusts; ``per_frame``; ...), a row each; ``--misfit`` gives every variant that misfit.

Methods, each run as the filter and as per-frame argmax (``localize`` around the previous estimate moved by the
odometry, the best candidate taken): ECR with the analytic, the learned and a uniform variance; NMI; NCC (16 bins,
window +-8 cells, 5 yaws 1 degree apart). ``--oracle`` adds oracle gating, a reference no tracker can run: each frame
searched about the truth, its match taken where it is within one cell of the truth, dead reckoning through the rest.
Errors are split along the true heading (longitudinal) and across it (lateral); "covered" is the share of frames whose
filter 95 % ellipse holds the truth.

    python -m data_tools.experiments.drive.drive                                     # the tables, ~3 min on 2 cores
    python -m data_tools.experiments.drive.drive --figure docs/images/drive.png      # and the docs' figure
    python -m data_tools.experiments.drive.drive --frames 60 --methods ecr_analytic  # a quick look
    python -m data_tools.experiments.drive.drive --scene-change 0.5 --seeds 0 1 2 --figure runs/drive/changed.png
    python -m data_tools.experiments.drive.drive --seeds 3 4 5 --methods ecr_analytic --variants held per_frame \
        binned --oracle                                                              # the tracker's score, paired
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from skimage import data

from data_tools.experiments.drive.variants import (
    DEFAULT_VARIANT,
    VARIANT_LABELS,
    add_variant_options,
    mean_and_error,
    paired_rows,
    variant_score,
)
from enmi_torch import GroundGrid, Localization, RoadCamera, rectify, unrectify
from enmi_torch.data.scene_change import scene_change
from enmi_torch.geometry.rectify import ground_to_image_homography
from enmi_torch.localization import NoCandidateError
from enmi_torch.localization.search import localize
from enmi_torch.scores import ECR, NCC, NMI, Score
from enmi_torch.tracking import (
    CHI2_95_2D,
    Calibration,
    Tracker,
    TrackerSettings,
    calibrate_temperature,
    initial_belief,
)
from enmi_torch.tracking.belief import check_mismatch_probability, finite_floor
from enmi_torch.tracking.health import peak_z_score
from enmi_torch.tracking.search import FrameSearch
from enmi_torch.utils.checks import value_checks
from enmi_torch.variance import empirical_variance
from enmi_torch.variance.perspective import homography_variance

CELL_CM = 2.5
GRID = GroundGrid((-80.0, 80.0), (40.0, 200.0), CELL_CM)
CAMERA = RoadCamera.paper((120, 160))
FRAME = GRID.shape  # (64, 64)
TILES = ("gravel", "grass", "brick", "camera", "moon")
ROAD_WIDTH = 320
SPEED = 9.0
PIXEL_NOISE = 6.0
SHIFTS = 8
YAW_BINS = 5
YAW_STEP = 1.0
BINS = 16
NOISY = (150, 180)
CHANGED = (60, 90)
# Each method's score and the variance it is given (None: a score without one).
METHODS = {
    "ecr_analytic": (ECR(bins=BINS), "analytic"),
    "ecr_learned": (ECR(bins=BINS), "learned"),
    "ecr_uniform": (ECR(bins=BINS), "uniform"),
    "nmi": (NMI(bins=BINS), None),
    "ncc": (NCC(), None),
}
LABELS = {
    "ecr_analytic": "ECR, analytic variance",
    "ecr_learned": "ECR, learned variance",
    "ecr_uniform": "ECR, uniform variance",
    "nmi": "NMI",
    "ncc": "NCC",
}
LOGDIR = Path("runs/drive")


def method_score(
    method: str, variant: str = DEFAULT_VARIANT, misfit: str | None = None
) -> tuple[Score, str | None, str]:
    """A method's score, variance kind and noise model: ECR's the ``variant``'s with ``BINS`` bins (and ``misfit``)."""
    score, kind = METHODS[method]
    if not isinstance(score, ECR):
        return score, kind, "per_frame"
    score, noise_model = variant_score(variant, bins=BINS, misfit=misfit)
    return score, kind, noise_model


def road_map() -> torch.Tensor:
    """``(1, 1, 2560, 320)`` float64 grey levels: the tiles bottom (start) to top, with painted markings."""
    tiles = [getattr(data, name)()[:, 96 : 96 + ROAD_WIDTH].astype(np.float64) for name in reversed(TILES)]
    image = np.concatenate(tiles, axis=0)
    paint = 235.0
    image[:, 20:26] = paint  # solid edge lines
    image[:, 294:300] = paint
    for start in range(0, image.shape[0], 64):  # dashed centre line: 32 cells painted, 32 not
        image[start : start + 32, 157:163] = paint
    for row in (2200, 1700, 700):  # stop bars across the right lane
        image[row : row + 8, 163:294] = paint
    return torch.from_numpy(image)[None, None]


def trajectory(frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    """True poses ``(frames, 3)`` ``(x, y, yaw)`` and true increments ``(frames, 3)`` ``(du, dv, dyaw)`` (row 0: 0).

    The vehicle moves up the map (forward is ``-v`` in the frame): each pose is the previous one moved by its
    increment turned by the previous yaw, the motion model of :func:`enmi_torch.tracking.predict`.
    """
    steps = torch.arange(frames, dtype=torch.float64)
    yaw = 6.0 * torch.sin(2 * math.pi * steps / 110) + 2.0 * torch.sin(2 * math.pi * steps / 37)
    speed = SPEED + 1.0 * torch.sin(2 * math.pi * steps / 53)
    increments = torch.zeros(frames, 3, dtype=torch.float64)
    increments[1:, 1] = -speed[1:]
    increments[1:, 2] = yaw[1:] - yaw[:-1]
    poses = torch.zeros(frames, 3, dtype=torch.float64)
    poses[0] = torch.tensor([ROAD_WIDTH * 0.7, 2560.0 - 150.0, float(yaw[0])])
    for index in range(1, frames):
        poses[index] = move(poses[index - 1], increments[index])
    return poses, increments


def move(pose: torch.Tensor, increment: torch.Tensor) -> torch.Tensor:
    """``pose`` moved by ``(du, dv, dyaw)`` in its frame's axes (as in :mod:`enmi_torch.tracking`)."""
    angle = math.radians(-float(pose[2]))
    cos, sin = math.cos(angle), math.sin(angle)
    du, dv, dyaw = increment.tolist()
    return pose + torch.tensor([cos * du + sin * dv, -sin * du + cos * dv, dyaw], dtype=pose.dtype)


def measured_odometry(increments: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Odometry with a 3 % scale error, a 0.05 degree yaw-rate bias and white noise (0.3 cells, 0.1 degrees)."""
    noise = torch.randn(increments.shape, generator=generator, dtype=torch.float64)
    measured = increments.clone()
    measured[:, :2] = increments[:, :2] * 1.03 + 0.3 * noise[:, :2]
    measured[:, 2] = increments[:, 2] + 0.05 + 0.1 * noise[:, 2]
    measured[0] = 0
    return measured


def ground_patches(world: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """``(N, 1, 64, 64)`` ground under each pose on the frame grid, bilinear (the map's cells are 2.5 cm too)."""
    transforms = Localization(poses, *(torch.zeros(len(poses)),) * 5).local_to_map(FRAME)
    rows, cols = torch.meshgrid(*(torch.arange(size, dtype=torch.float64) for size in FRAME), indexing="ij")
    points = torch.stack([cols.flatten(), rows.flatten(), torch.ones(rows.numel(), dtype=torch.float64)])
    mapped = transforms @ points
    height, width = world.shape[2:]
    grid = torch.stack([mapped[:, 0] / (width - 1), mapped[:, 1] / (height - 1)], -1) * 2 - 1
    grid = grid.reshape(len(poses), *FRAME, 2)
    return F.grid_sample(world.expand(len(poses), -1, -1, -1), grid, align_corners=True, padding_mode="border")


def render(patches: torch.Tensor, pixel_noise: torch.Tensor, generator: torch.Generator):
    """Frames seen through the camera: ground into the camera, pixel noise, rectified back. Returns frames, valid."""
    image, _ = unrectify(patches, CAMERA, GRID)
    noise = torch.randn(image.shape, generator=generator, dtype=image.dtype) * pixel_noise[:, None, None, None]
    frames, valid = rectify(image + noise, CAMERA, GRID, supersample=4)
    return frames, valid


def respond(values: torch.Tensor) -> torch.Tensor:
    """The changed appearance: a non-monotonic response (mid-grey bright, dark and white both dark)."""
    return 255 * (2 * values.clamp(0, 255) / 255 - 1).abs() ** 0.8


def changed_scene(image: torch.Tensor, seed: int, strength: float) -> torch.Tensor:
    """The road as the drive sees it: ``image`` changed in 512-row pieces, each with its own draws of every change."""
    pieces = [scene_change(piece, seed * 1000 + index, strength) for index, piece in enumerate(image.split(512, dim=0))]
    return torch.cat(pieces, 0)


def analytic_variance() -> torch.Tensor:
    """``(1, 1, 64, 64)`` ``N0 / A`` per unit pixel noise variance."""
    return homography_variance(ground_to_image_homography(CAMERA, GRID), FRAME, 1.0)


class Drive:
    """The drive: map, truth, odometry, frames with their noise level, calibration frames.

    ``scene_change`` in ``[0, 1]``: the frames see the road changed since the map was made
    (:func:`enmi_torch.data.scene_change`, every kind mixed at that strength: illumination, cast shadows, occluders
    pasted from other photographs, tone, resampling and blur, parallax warps), the map stays as it was;
    ``noise_scale`` multiplies the pixel noise.
    """

    def __init__(self, frames: int, seed: int, scene_change: float = 0.0, noise_scale: float = 1.0) -> None:
        generator = torch.Generator().manual_seed(seed)
        self.map = road_map()
        self.world = self.map
        if scene_change > 0:
            self.world = changed_scene(self.map[0, 0], seed, scene_change)[None, None]
        self.truth, increments = trajectory(frames)
        self.odometry = measured_odometry(increments, generator)
        index = torch.arange(frames)
        noisy = (index >= NOISY[0]) & (index < NOISY[1])
        changed = (index >= CHANGED[0]) & (index < CHANGED[1])
        self.pixel_noise = torch.where(noisy, 4 * PIXEL_NOISE, PIXEL_NOISE).double() * noise_scale
        self.noise_scale = noise_scale
        patches = ground_patches(self.world, self.truth)
        patches = torch.where(changed[:, None, None, None], respond(patches), patches)
        self.frames, self.valid = render(patches, self.pixel_noise, generator)
        self.hard = {"strong noise": noisy, "changed appearance": changed, "brick": self._on_tile("brick")}
        self._calibration_set(generator, increments)

    def _on_tile(self, name: str) -> torch.Tensor:
        tile = list(reversed(TILES)).index(name)
        return (self.truth[:, 1] >= tile * 512) & (self.truth[:, 1] < (tile + 1) * 512)

    def _calibration_set(self, generator: torch.Generator, increments: torch.Tensor) -> None:
        """Held-out frames at random poses (noise levels as in the drive) and a held-out odometry sequence."""
        count = 64
        poses = torch.stack(
            [
                60 + torch.rand(count, generator=generator, dtype=torch.float64) * (ROAD_WIDTH - 120),
                100 + torch.rand(count, generator=generator, dtype=torch.float64) * (2560 - 200),
                (torch.rand(count, generator=generator, dtype=torch.float64) - 0.5) * 12,
            ],
            1,
        )
        noise = torch.where(torch.rand(count, generator=generator) < 0.2, 4 * PIXEL_NOISE, PIXEL_NOISE).double()
        noise = noise * self.noise_scale
        changed = torch.rand(count, generator=generator) < 0.2
        patches = ground_patches(self.world, poses)
        patches = torch.where(changed[:, None, None, None], respond(patches), patches)
        self.held_out_poses = poses
        self.held_out_noise = noise
        self.held_out_frames, _ = render(patches, noise, generator)
        # The learned variance: residuals of held-out renders against their noiseless rendering, per unit variance.
        clean, _ = render(patches, torch.zeros(count, dtype=torch.float64), generator)
        unit = (self.held_out_frames - clean) / noise[:, None, None, None]
        variance, observed = empirical_variance(unit, torch.zeros_like(unit), self.valid.expand_as(unit))
        self.learned_unit = torch.where(observed, variance, 1.0).reshape(1, 1, *FRAME)
        errors = measured_odometry(increments, generator) - increments
        self.motion_noise = tuple(errors[1:].square().mean(0).sqrt().tolist())

    def variance(self, kind: str | None, pixel_noise: torch.Tensor, uniform_scale: float = 1.0) -> torch.Tensor | None:
        """``(N, 1, 64, 64)`` variance of frames with these pixel noise levels, or ``None``.

        ``uniform_scale``: the uniform variance is this factor times the learned map's mean (the grid of controls).
        """
        if kind is None:
            return None
        unit = {"analytic": analytic_variance(), "learned": self.learned_unit}.get(kind)
        if kind == "uniform":
            unit = torch.full_like(self.learned_unit, uniform_scale * float(self.learned_unit[self.valid].mean()))
        return (unit * pixel_noise[:, None, None, None].square()).float()


def calibrate(drive: Drive, method: str, misfit: str | None = None, variant: str = DEFAULT_VARIANT) -> Calibration:
    """Temperature and peak z threshold of one method from the held-out frames.

    With a held noise model each frame is searched with the model read at its true cell and yaw bin, as a tracker
    that trusts that frame would hold it (:meth:`~enmi_torch.tracking.search.FrameSearch.held_fit`).
    """
    score, kind, noise_model = method_score(method, variant, misfit)
    variance = drive.variance(kind, drive.held_out_noise)
    generator = torch.Generator().manual_seed(1)
    offsets = torch.randint(-4, 5, (len(drive.held_out_poses), 2), generator=generator)
    truth_cells = drive.held_out_poses[:, [1, 0]]
    centers = truth_cells.round().long() + offsets
    yaw_centers = drive.held_out_poses[:, 2].round()
    surfaces, aligned_z = [], []
    count = int(drive.valid.sum())
    for index in range(len(centers)):
        frame_variance = None if variance is None else variance[index : index + 1]
        frame = drive.held_out_frames[index : index + 1].float()
        yaws = (yaw_centers[index] + torch.arange(-2.0, 3.0) * YAW_STEP).tolist()
        frame_score = score
        if noise_model == "held":
            frame_score = held_at_truth(drive, index, frame_variance, score)
        surface = search(frame, drive.map.float(), frame_variance, drive.valid, centers[index], yaws, frame_score)
        surfaces.append(surface.surface[0].double())
        # The tracker's z-score: over the log-likelihood in nats, its spread at least one nat.
        aligned_z.append(float(peak_z_score(finite_floor(surface.surface[0].double()) * count, min_spread=1.0)))
    grid_truth = torch.stack(
        [
            truth_cells[:, 0] - centers[:, 0] + SHIFTS,
            truth_cells[:, 1] - centers[:, 1] + SHIFTS,
            (drive.held_out_poses[:, 2] - yaw_centers) / YAW_STEP + 2,
        ],
        1,
    )
    temperature = calibrate_temperature(torch.stack(surfaces) * count, grid_truth)
    # Aligned frames pass 95 % of the time; wrong windows are caught by the prediction (surprise) instead.
    threshold = float(torch.tensor(aligned_z).quantile(0.05))
    return Calibration(score.name, temperature, threshold, noise_model)


def held_at_truth(drive: Drive, index: int, variance: torch.Tensor | None, score: Score) -> Score:
    """``score`` with its noise model read on held-out frame ``index`` at its true cell and yaw bin, held."""
    pose = drive.held_out_poses[index : index + 1].clone()
    pose[:, :2] = pose[:, :2].round()
    pose[:, 2] = pose[:, 2].round()
    belief = initial_belief(pose, shifts=0, yaw_bins=1, yaw_step=YAW_STEP)
    frame = drive.held_out_frames[index : index + 1].float()
    found = FrameSearch(frame, drive.map.float(), variance, drive.valid, score)
    return found.held_fit(0, belief, torch.zeros(1, 1, 1, dtype=torch.float64))


def search(frame, reference, variance, valid, center, yaws, score: Score) -> Localization:
    """The benchmark's one ``localize`` call (+-8 cells): ``frame`` ``(1, 1, 64, 64)`` around map cell ``center``.

    ``center`` is ``(row, col)``, as the belief's window keeps it.
    """
    return localize(
        frame, reference, variance, score=score, shifts=SHIFTS, around=center.flip(0), yaws=yaws, captured_mask=valid
    )


def run_filter(
    drive: Drive,
    method: str,
    calibration: Calibration | None = None,
    refine: bool = False,
    coasting: str = "random_walk",
    uniform_scale: float = 1.0,
    misfit: str | None = None,
    mismatch_probability: float = 0.0,
    variant: str = DEFAULT_VARIANT,
) -> dict:
    """Poses, covariances, health and relocalization per frame of the filter (uncalibrated without ``calibration``)."""
    score, kind, noise_model = method_score(method, variant, misfit)
    variance = drive.variance(kind, drive.pixel_noise, uniform_scale)
    settings = TrackerSettings(
        motion_noise=drive.motion_noise,
        coasting=coasting,
        refine=refine and method != "nmi",
        mismatch_probability=mismatch_probability,
    )
    if calibration is None:  # a calibration sets the noise model it was fitted with
        settings = settings.replace(noise_model=noise_model)
    tracker = Tracker(
        drive.map.float(),
        calibration=calibration,
        score=score,
        shifts=SHIFTS,
        yaw_bins=YAW_BINS,
        yaw_step=YAW_STEP,
        settings=settings,
    )
    tracker.start(drive.truth[:1], std=(2.0, 2.0, 1.0))
    poses, covariances, healthy, relocalized, seconds = [drive.truth[0]], [torch.eye(3) * 0.0], [True], [False], []
    lost = [False]
    refined = [torch.full((3,), math.nan, dtype=torch.float64)]
    for index in range(1, len(drive.truth)):
        frame_variance = None if variance is None else variance[index : index + 1]
        start = time.perf_counter()
        output = tracker(
            drive.frames[index : index + 1].float(), drive.odometry[index : index + 1], frame_variance, drive.valid
        )
        seconds.append(time.perf_counter() - start)
        poses.append(output.pose[0])
        covariances.append(output.covariance[0])
        healthy.append(bool(output.healthy[0]))
        relocalized.append(bool(output.relocalized[0]))
        lost.append(bool(output.lost[0]))
        refined.append(output.refined[0].double())
    return {
        "pose": torch.stack(poses),
        "covariance": torch.stack(covariances).double(),
        "healthy": torch.tensor(healthy),
        "relocalized": torch.tensor(relocalized),
        "lost": torch.tensor(lost),
        "refined": torch.stack(refined),
        "seconds": torch.tensor(seconds),
    }


def run_argmax(
    drive: Drive, method: str, uniform_scale: float = 1.0, misfit: str | None = None, variant: str = DEFAULT_VARIANT
) -> dict:
    """Per-frame argmax: search around the previous estimate moved by the odometry, keep the best candidate."""
    score, kind, _ = method_score(method, variant, misfit)
    variance = drive.variance(kind, drive.pixel_noise, uniform_scale)
    poses = [drive.truth[0]]
    for index in range(1, len(drive.truth)):
        guess = _moved(poses[-1], drive.odometry[index])
        center = torch.stack([guess[1], guess[0]]).round().long()
        yaw_center = round(float(guess[2]))
        try:
            result = search(
                drive.frames[index : index + 1].float(),
                drive.map.float(),
                None if variance is None else variance[index : index + 1],
                drive.valid,
                center,
                [yaw_center + step * YAW_STEP for step in range(-2, 3)],
                score,
            )
        except NoCandidateError:  # the guess has left the map: keep dead reckoning
            poses.append(guess)
            continue
        poses.append(result.pose[0].double())
    return {"pose": torch.stack(poses)}


def run_oracle_gating(
    drive: Drive, method: str, uniform_scale: float = 1.0, misfit: str | None = None, variant: str = DEFAULT_VARIANT
) -> dict:
    """A reference, not a method: dead reckoning told which frames' best match is right.

    Each frame is searched in the filter's window (``SHIFTS`` cells, ``YAW_BINS`` yaws) about its true cell and yaw;
    where the best candidate is within one cell of the truth on both map axes it is taken, elsewhere the last pose
    moved by the odometry. It shows how much of a drive the frames and the odometry leave to be lost even by a filter
    that never takes a wrong match (not a strict bound: a filter may use a match off by more than a cell).
    """
    score, kind, _ = method_score(method, variant, misfit)
    variance = drive.variance(kind, drive.pixel_noise, uniform_scale)
    poses = [drive.truth[0]]
    for index in range(1, len(drive.truth)):
        truth = drive.truth[index]
        found = None
        try:
            found = (
                search(
                    drive.frames[index : index + 1].float(),
                    drive.map.float(),
                    None if variance is None else variance[index : index + 1],
                    drive.valid,
                    torch.stack([truth[1], truth[0]]).round().long(),
                    [round(float(truth[2])) + step * YAW_STEP for step in range(-2, 3)],
                    score,
                )
                .pose[0]
                .double()
            )
        except NoCandidateError:
            pass
        if found is not None and bool((found[:2] - truth[:2]).abs().max() <= 1):
            poses.append(found)
        else:
            poses.append(_moved(poses[-1], drive.odometry[index]))
    return {"pose": torch.stack(poses)}


def _moved(pose: torch.Tensor, increment: torch.Tensor) -> torch.Tensor:
    return move(pose.double(), increment.double())


def dead_reckoning(drive: Drive) -> torch.Tensor:
    poses = [drive.truth[0]]
    for index in range(1, len(drive.truth)):
        poses.append(_moved(poses[-1], drive.odometry[index]))
    return torch.stack(poses)


def errors(truth: torch.Tensor, pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Longitudinal and lateral errors in cells, along and across the true heading."""
    difference = pose[:, :2] - truth[:, :2]
    heading = torch.deg2rad(truth[:, 2])
    forward = torch.stack([heading.sin(), -heading.cos()], 1)
    right = torch.stack([heading.cos(), heading.sin()], 1)
    return (difference * forward).sum(1), (difference * right).sum(1)


def summary(truth: torch.Tensor, pose: torch.Tensor, frames: torch.Tensor | None = None) -> dict:
    longitudinal, lateral = errors(truth, pose)
    if frames is not None:
        longitudinal, lateral = longitudinal[frames], lateral[frames]
    within = (longitudinal.abs() <= 1) & (lateral.abs() <= 1)
    return {
        "lateral_rms": float(lateral.square().mean().sqrt()),
        "lateral_max": float(lateral.abs().max()),
        "longitudinal_rms": float(longitudinal.square().mean().sqrt()),
        "longitudinal_max": float(longitudinal.abs().max()),
        "within_1_cell": float(within.double().mean()),
    }


def coverage(truth: torch.Tensor, result: dict) -> float:
    """Share of frames (after the first) whose 95 % (x, y) ellipse holds the true position."""
    difference = (result["pose"][1:, :2] - truth[1:, :2])[..., None]
    covariance = result["covariance"][1:, :2, :2]
    distance = (difference.transpose(1, 2) @ torch.linalg.solve(covariance, difference))[:, 0, 0]
    return float((distance <= CHI2_95_2D).double().mean())


def print_tables(drive: Drive, results: dict, calibrations: dict) -> list[str]:
    lines = [
        f"\n{len(drive.truth)} frames, {CELL_CM} cm cells; errors in cells (cm); within 1 cell on both axes\n",
        "| method | estimator | lateral RMS | lateral max | longitudinal RMS | longitudinal max | within 1 cell | "
        "95 % ellipse covers | relocalized |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]

    def cells(value: float) -> str:
        return f"{value:.2f} ({value * CELL_CM:.1f})"

    rows = [("odometry only", "dead reckoning", summary(drive.truth, dead_reckoning(drive)), None, None)]
    for method, (filtered, argmax) in results.items():
        rows.append((method, "filter", summary(drive.truth, filtered["pose"]), filtered, method))
        rows.append((method, "per-frame argmax", summary(drive.truth, argmax["pose"]), None, method))
    for label, estimator, stats, filtered, _ in rows:
        covered = f"{coverage(drive.truth, filtered):.3f}" if filtered is not None else "-"
        relocalized = str(int(filtered["relocalized"].sum())) if filtered is not None else "-"
        lines.append(
            f"| {label} | {estimator} | {cells(stats['lateral_rms'])} | {cells(stats['lateral_max'])} | "
            f"{cells(stats['longitudinal_rms'])} | {cells(stats['longitudinal_max'])} | {stats['within_1_cell']:.3f} | "
            f"{covered} | {relocalized} |"
        )
    lines += ["\nHard stretches: lateral RMS / longitudinal RMS in cells, filter (argmax)\n"]
    names = list(drive.hard)
    lines += ["| method | " + " | ".join(names) + " |", "|" + " --- |" * (len(names) + 1)]
    for method, (filtered, argmax) in results.items():
        parts = []
        for name in names:
            frames = drive.hard[name]
            if not bool(frames.any()):
                parts.append("-")
                continue
            mine, theirs = summary(drive.truth, filtered["pose"], frames), summary(drive.truth, argmax["pose"], frames)
            parts.append(
                f"{mine['lateral_rms']:.2f} / {mine['longitudinal_rms']:.2f} "
                f"({theirs['lateral_rms']:.2f} / {theirs['longitudinal_rms']:.2f})"
            )
        lines.append(f"| {method} | " + " | ".join(parts) + " |")
    if calibrations:
        lines += ["\nCalibration (held-out frames): temperature, peak z threshold\n"]
    for method, calibration in calibrations.items():
        lines.append(f"- {method}: T = {calibration.temperature:.3g}, min_peak_z = {calibration.min_peak_z:.2f}")
    lines.append(
        f"- odometry noise (RMS increment error du, dv, dyaw): {tuple(round(v, 3) for v in drive.motion_noise)}"
    )
    return lines


def plot(drive: Drive, results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(13, 6.5), gridspec_kw={"width_ratios": [1.1, 2, 2]})
    axes[0].imshow(drive.map[0, 0].numpy(), cmap="gray", aspect="auto")
    reckoning = dead_reckoning(drive)
    axes[0].plot(drive.truth[:, 0], drive.truth[:, 1], "g-", lw=2, label="truth")
    axes[0].plot(reckoning[:, 0], reckoning[:, 1], "r--", lw=1.2, label="odometry")
    first = next(iter(results))
    axes[0].plot(results[first][0]["pose"][:, 0], results[first][0]["pose"][:, 1], "c-", lw=1, label="filter")
    axes[0].set(title="trajectory (map cells)", xlim=(0, ROAD_WIDTH))
    axes[0].legend(fontsize=7, loc="lower left")
    frames = np.arange(len(drive.truth))
    for axis, component, name in ((axes[1], 1, "lateral"), (axes[2], 0, "longitudinal")):
        for method, (filtered, argmax) in results.items():
            line = axis.plot(frames, errors(drive.truth, filtered["pose"])[component].abs() * CELL_CM, lw=1.2)
            axis.plot(
                frames,
                errors(drive.truth, argmax["pose"])[component].abs() * CELL_CM,
                ":",
                color=line[0].get_color(),
                lw=0.9,
            )
            line[0].set_label(f"{method}: filter (solid), argmax (dotted)")
        for start, stop, label in ((*NOISY, "strong noise"), (*CHANGED, "changed")):
            axis.axvspan(start, stop, color="orange", alpha=0.15)
            axis.text(start, 0.9, label, transform=axis.get_xaxis_transform(), fontsize=7)
        brick = drive.hard["brick"].nonzero()[:, 0]
        if len(brick):
            axis.axvspan(int(brick[0]), int(brick[-1]), color="purple", alpha=0.08)
            axis.text(int(brick[0]), 0.95, "brick", transform=axis.get_xaxis_transform(), fontsize=7)
        axis.set(yscale="log", ylim=(0.05, 500), xlabel="frame", ylabel=f"|{name} error| (cm)", title=f"{name} error")
        axis.axhline(CELL_CM, color="k", lw=0.6, ls="--")
    axes[1].legend(fontsize=7, loc="upper right")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)


def log_tensorboard(drive: Drive, results: dict, folder: Path) -> Path | None:
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    writer = SummaryWriter(str(folder))
    for method, (filtered, argmax) in results.items():
        for estimator, result in (("filter", filtered), ("argmax", argmax)):
            longitudinal, lateral = errors(drive.truth, result["pose"])
            for index in range(len(drive.truth)):
                writer.add_scalars(
                    f"{method}/{estimator}",
                    {
                        "lateral_cm": float(lateral[index]) * CELL_CM,
                        "longitudinal_cm": float(longitudinal[index]) * CELL_CM,
                    },
                    index,
                )
    writer.close()
    return folder


def refined_table(drive: Drive, results: dict) -> list[str]:
    """The filter's pose against each used frame's refined pose (``Tracker(refine=True)``), over those frames."""
    lines = [
        "\nRefined (each used frame registered from the filter's pose), over the frames refined\n",
        "| method | frames | filter: position RMS | refined: position RMS | filter: yaw RMS | refined: yaw RMS |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for method, (filtered, _) in results.items():
        done = torch.isfinite(filtered["refined"][:, 0])
        if not bool(done.any()):
            continue
        truth = drive.truth[done]
        parts = []
        for pose in (filtered["pose"][done], filtered["refined"][done]):
            parts.append(float((pose[:, :2] - truth[:, :2]).square().sum(1).mean().sqrt()))
        for pose in (filtered["pose"][done], filtered["refined"][done]):
            parts.append(float((pose[:, 2] - truth[:, 2]).square().mean().sqrt()))
        values = " | ".join(f"{value:.3f}" for value in parts)
        lines.append(f"| {method} | {int(done.sum())} | {values} |")
    return lines


def lost_share(truth: torch.Tensor, pose: torch.Tensor) -> float:
    """Share of frames (after the first) more than 4 cells from the truth."""
    return float(((pose[1:, :2] - truth[1:, :2]).norm(dim=1) > 4).double().mean())


def across_drives(rows: dict) -> list[str]:
    """Mean ± SE over the drives of each row (a method's label and its estimator), and each row less the first."""
    lines = [
        "\nAcross drives: mean ± SE (drives that raised an exception are counted, not averaged)\n",
        "| method | estimator | drives | within 1 cell | lost (> 4 cells) | RMS error (cells) | 95 % ellipse covers "
        "| raised |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    paired = {}
    for (label, estimator), values in rows.items():
        done = [value for value in values if value is not None]
        parts = []
        for key in MEASURES:
            column = [value[key] for value in done if value.get(key) is not None]
            parts.append(mean_and_error(column))
            if len(done) == len(values) and len(column) == len(values):
                paired.setdefault(f"{label} | {estimator}", {})[key] = column
        raised = len(values) - len(done)
        lines.append(f"| {label} | {estimator} | {len(values)} | " + " | ".join(parts) + f" | {raised} |")
    drives = max((len(values) for values in rows.values()), default=0)
    return lines + paired_rows(paired, drives, MEASURES)


MEASURES = ("within", "lost", "rms", "covered")  # a drive's row: within 1 cell, lost, RMS error, ellipse covers


def _drive_row(drive: Drive, result: dict, filtered: bool) -> dict:
    stats = summary(drive.truth, result["pose"])
    rms = float((result["pose"][1:, :2] - drive.truth[1:, :2]).square().sum(1).mean().sqrt())
    return {
        "within": stats["within_1_cell"],
        "lost": lost_share(drive.truth, result["pose"]),
        "rms": rms,
        "covered": coverage(drive.truth, result) if filtered else None,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.epilog = "examples:\n" + __doc__.rsplit("\n\n", 1)[1]
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--frames", type=int, default=240, help="frames of the drive")
    parser.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="a drive per seed: noise, odometry, change")
    parser.add_argument("--scene-change", type=float, default=0.0, help="strength in [0, 1] of the road's change")
    parser.add_argument("--noise-scale", type=float, default=1.0, help="factor on the pixel noise")
    parser.add_argument("--calibrate", action="store_true", help="fit each score's temperature on held-out frames")
    parser.add_argument("--refine", action="store_true", help="also register each used frame (ECR and NCC)")
    parser.add_argument(
        "--coasting",
        choices=["random_walk", "linear"],
        default="random_walk",
        help="how the belief widens without a match (Tracker's coasting)",
    )
    parser.add_argument(
        "--uniform-scale",
        type=float,
        default=1.0,
        help="the uniform variance as this factor times the learned map's mean (default 1: the mean)",
    )
    add_variant_options(parser)
    parser.add_argument("--oracle", action="store_true", help="also oracle gating: each frame searched about the truth")
    parser.add_argument(
        "--mismatch-probability",
        type=float,
        default=0.0,
        help="the filter's chance that a frame matched some other place (Tracker's mismatch_probability)",
    )
    parser.add_argument("--figure", type=Path, help="draw the first drive's track and errors into this PNG")
    parser.add_argument("--logdir", type=Path, default=LOGDIR, help="calibration files and TensorBoard logs")
    args = parser.parse_args(argv)
    if not 0 <= args.scene_change <= 1:
        parser.error(f"--scene-change must be in [0, 1], got {args.scene_change}")
    if not args.noise_scale > 0:
        parser.error(f"--noise-scale must be > 0, got {args.noise_scale}")
    if not (math.isfinite(args.uniform_scale) and args.uniform_scale > 0):
        parser.error(f"--uniform-scale must be a finite number > 0, got {args.uniform_scale}")
    try:
        check_mismatch_probability(args.mismatch_probability)  # the tracker's own bound
    except ValueError:
        parser.error(f"--mismatch-probability must be in [0, 1), got {args.mismatch_probability}")
    torch.set_num_threads(1)
    if args.uniform_scale != 1:
        print(f"ECR, uniform variance: {args.uniform_scale:g} x the learned map's mean", flush=True)
    variants = list(dict.fromkeys(args.variants))
    shown = ", ".join(VARIANT_LABELS[variant] for variant in variants)
    misfit = "as each variant" if args.misfit is None else repr(args.misfit)
    print(f"ECR {shown}; misfit {misfit}; mismatch probability {args.mismatch_probability:g}", flush=True)
    start = time.perf_counter()
    runs = [
        (method, variant) for method in args.methods for variant in (variants if method.startswith("ecr") else [None])
    ]
    estimators = ("filter", "per-frame argmax", *(["oracle gating"] if args.oracle else []))
    rows = {}
    for number, seed in enumerate(args.seeds):
        drive = Drive(args.frames, seed, args.scene_change, args.noise_scale)
        results, calibrations, searched = {}, {}, {}
        for method, variant in runs:
            label = LABELS[method] + (f", {VARIANT_LABELS[variant]}" if variant and len(variants) > 1 else "")
            variant = variant or DEFAULT_VARIANT
            score = method_score(method, variant, args.misfit)[0]
            # Featureless frames (the photograph's sky) are no error here: their flat surfaces are weak matches.
            with value_checks(False):
                calibration = calibrate(drive, method, args.misfit, variant) if args.calibrate else None
                if calibration is not None:
                    calibrations[label] = calibration
                try:
                    filtered = run_filter(
                        drive,
                        method,
                        calibration,
                        args.refine,
                        args.coasting,
                        args.uniform_scale,
                        args.misfit,
                        args.mismatch_probability,
                        variant,
                    )
                except Exception as error:  # a drive that raises is a result, reported as such
                    print(f"seed {seed} {label}: the filter raised {type(error).__name__}: {error}", flush=True)
                    filtered = None
                # Per-frame searches of one score run once: a held noise model is the filter's only.
                for estimator, run in (("per-frame argmax", run_argmax), ("oracle gating", run_oracle_gating)):
                    if estimator in estimators and (estimator, method, score) not in searched:
                        found = run(drive, method, args.uniform_scale, args.misfit, variant)
                        searched[estimator, method, score] = found
            rows.setdefault((label, "filter"), []).append(
                None if filtered is None else _drive_row(drive, filtered, True)
            )
            for estimator in estimators[1:]:
                rows.setdefault((label, estimator), []).append(
                    _drive_row(drive, searched[estimator, method, score], False)
                )
            if filtered is not None:
                results[label] = (filtered, searched["per-frame argmax", method, score])
            print(f"drive {number + 1}/{len(args.seeds)} {label}: {time.perf_counter() - start:.0f} s", flush=True)
        print(f"\n## Drive seed {seed}")
        print("\n".join(print_tables(drive, results, calibrations)))
        if args.refine:
            print("\n".join(refined_table(drive, results)))
        if number == 0 and results:
            folder = args.logdir
            folder.mkdir(parents=True, exist_ok=True)
            for (method, variant), calibration in zip(runs, calibrations.values(), strict=False):
                calibration.save(folder / f"calibration_{method}{'_' + variant if variant else ''}.json")
            if args.figure is not None:
                plot(drive, results, args.figure)
                print(f"wrote {args.figure}")
            logged = log_tensorboard(drive, results, folder / "tensorboard")
            step_ms = {label: 1000 * float(pair[0]["seconds"].median()) for label, pair in results.items()}
            print(f"\nmedian filter step (ms): {json.dumps({k: round(v, 1) for k, v in step_ms.items()})}")
            if logged:
                print(f"wrote TensorBoard logs in {logged}")
    print("\n".join(across_drives(rows)))
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
