"""A variance mask learned from local/prior pairs by maximum likelihood, optionally smooth or of a parametric form.

The residual ``r = captured - reference`` of a matching (local, prior) pair is modelled as ``N(0, sigma^2[i, j])``
per pixel. The model holds ``s = log sigma^2`` — one value per pixel (``form="pixel"``), or
``s = sum_k c_k phi_k[i, j]`` over a fixed basis (``"radial"``: polynomials of the distance from the vehicle;
``"perspective"``: the log of an analytic map such as the camera's ``N0 / A~``) when few pairs are at hand — and is
fitted by minimising the Gaussian negative log-likelihood :func:`gaussian_nll`, plus an optional Gaussian smoothness
prior on neighbouring log-variances.

Convention:
    The per-pixel maximum-likelihood variance of zero-mean residuals is the mean of the squared residuals,
    ``1 / n sum_k r_k^2``: the paper's empirical mask (:func:`~enmi_torch.variance.empirical_variance`, which
    divides by ``n - 1``) is larger by the factor ``n / (n - 1)``, 0.05 % for 2,000 pairs.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from enmi_torch.utils.budget import MemoryBudgetError, budget_error, check_cells_memory, within_budget
from enmi_torch.utils.checks import (
    check_finite_where,
    check_floating,
    check_image_shape,
    check_non_negative_int,
    check_not_empty,
    check_option,
    check_positive_number,
    check_some_pixel,
    check_tensor,
)
from enmi_torch.utils.files import check_file_to_write, load_plain_torch, read_npy
from enmi_torch.utils.layout import broadcast_map, mask_map
from enmi_torch.variance.base import VarianceModel

FORMS = ("pixel", "radial", "perspective")
REDUCTIONS = ("none", "sum", "mean")
FILE_FORMAT = "enmi_torch.LearnedVariance"
FILE_VERSION = 1
_LOG_2PI = math.log(2 * math.pi)


def gaussian_nll(
    residual: Tensor, log_variance: Tensor, valid_mask: Tensor | None = None, *, reduction: str = "mean"
) -> Tensor:
    """Negative log-likelihood ``(r^2 / sigma^2 + log sigma^2 + log 2 pi) / 2`` of residuals under ``N(0, sigma^2)``.

    Args:
        residual: ``captured - reference``, ``(B, 1, H, W)`` or ``(B, H, W)``, floating point.
        log_variance: ``log sigma^2``, ``(H, W)``, ``(1, 1, H, W)`` or one map per sample.
        valid_mask: optional bool map, broadcast like ``log_variance``; ``False`` pixels are left out (they may hold
            NaN) and get no gradient.
        reduction: ``"none"`` (per pixel, ``(B, H*W)``, 0 where masked), ``"sum"`` or ``"mean"`` (over valid pixels).

    Returns:
        The NLL in nats, in the dtype of ``residual``.

    Convention:
        Differentiable in ``residual`` and ``log_variance``. Its minimiser over a constant ``log_variance`` is the
        log of the mean squared residual.

    Example:
        >>> gaussian_nll(torch.zeros(1, 1, 2, 2), torch.zeros(2, 2))
        tensor(0.9189)
    """
    check_floating("residual", residual)
    check_floating("log_variance", log_variance)
    check_option("reduction", reduction, REDUCTIONS)
    if residual.ndim not in (3, 4):
        raise ValueError(f"residual must have shape (B, 1, H, W) or (B, H, W), got {tuple(residual.shape)}")
    check_not_empty("residual", residual)
    flat = residual.reshape(residual.shape[0], -1)
    log_map = broadcast_map("log_variance", log_variance, residual, "residual").to(flat.dtype)
    valid = None
    if valid_mask is not None:
        valid = mask_map("valid_mask", valid_mask, residual, "residual", require_pixels=False)
    check_finite_where("residual", flat, valid)
    if valid is not None:
        # where() rather than a product: masked pixels may hold NaN and must pass no gradient. The map is masked
        # where no sample uses it, at its own size (a shared map is not expanded to the batch).
        used = valid if log_map.shape[0] == flat.shape[0] else valid.any(dim=0, keepdim=True)
        flat = torch.where(valid, flat, 0.0)
        log_map = torch.where(used, log_map, 0.0)
        check_finite_where("log_variance", log_map, used)
    else:
        check_finite_where("log_variance", log_map, None)
    # A zero residual adds 0 whatever sigma^2: exp(-log_map) may overflow there (log_variance=-1000) and 0 * inf is NaN.
    zero = flat == 0
    terms = 0.5 * (flat.square() * torch.exp(-torch.where(zero, 0.0, log_map)) + log_map + _LOG_2PI)
    if valid is not None:
        terms = torch.where(valid, terms, 0.0)
    if reduction == "none":
        return terms
    total = terms.sum()
    if reduction == "sum":
        return total
    if valid is None:
        return total / flat.numel()
    check_some_pixel("valid_mask", valid, "the mean NLL over no pixel is undefined; pass reduction='sum'")
    return total / valid.sum()


def smoothness_penalty(log_variance: Tensor, valid: Tensor | None = None) -> Tensor:
    """``1/2 sum (s_p - s_q)^2`` over the 4-neighbour pixel pairs ``(p, q)`` of an ``(H, W)`` map, both valid.

    The negative log of a Gaussian random-field prior (up to its precision): it pulls each pixel's log-variance
    towards its neighbours', never across the border of the valid region.

    Example:
        >>> smoothness_penalty(torch.tensor([[0.0, 1.0], [0.0, 1.0]]))
        tensor(1.)
    """
    check_floating("log_variance", log_variance)
    if log_variance.ndim != 2:
        raise ValueError(f"log_variance must have shape (H, W), got {tuple(log_variance.shape)}")
    if valid is None:
        valid = torch.ones_like(log_variance, dtype=torch.bool)
    elif valid.shape != log_variance.shape or valid.dtype != torch.bool:
        raise ValueError(
            f"valid must be a bool map of shape {tuple(log_variance.shape)}, got {valid.dtype} {tuple(valid.shape)}"
        )
    safe = torch.where(valid, log_variance, 0.0)
    down = torch.where(valid[1:] & valid[:-1], safe[1:] - safe[:-1], 0.0)
    right = torch.where(valid[:, 1:] & valid[:, :-1], safe[:, 1:] - safe[:, :-1], 0.0)
    return 0.5 * (down.square().sum() + right.square().sum())


def radial_basis(shape: tuple[int, int], degree: int, center: tuple[float, float] | None = None) -> Tensor:
    """Shifted Legendre polynomials ``P_k(2 rho - 1)``, ``k = 0..degree``, of the distance ``rho`` from ``center``.

    ``rho`` is the pixel distance from ``center`` (``(row, column)``, default the image centre, where the vehicle
    sits in the paper's masks) divided by the largest such distance in the image, so ``rho`` is in ``[0, 1]``. The
    polynomials span the same functions as the powers ``rho^k`` but are near-orthogonal, so gradient-based fits of
    their coefficients converge quickly. Returns ``(degree + 1, H, W)`` float64.

    Example:
        >>> radial_basis((3, 3), 1)[1]
        tensor([[ 1.0000,  0.4142,  1.0000],
                [ 0.4142, -1.0000,  0.4142],
                [ 1.0000,  0.4142,  1.0000]], dtype=torch.float64)
    """
    height, width = check_image_shape("shape", shape)
    check_non_negative_int("degree", degree)
    row0, col0 = _center(center, (height, width))
    rows = torch.arange(height, dtype=torch.float64).unsqueeze(1) - row0
    cols = torch.arange(width, dtype=torch.float64).unsqueeze(0) - col0
    distance = torch.sqrt(rows.square() + cols.square())
    argument = 2 * distance / distance.max().clamp_min(1.0) - 1
    # Bonnet's recursion: (k + 1) P_{k+1} = (2k + 1) x P_k - k P_{k-1}.
    polynomials = [torch.ones_like(argument), argument][: degree + 1]
    for order in range(1, degree):
        polynomials.append(
            ((2 * order + 1) * argument * polynomials[order] - order * polynomials[order - 1]) / (order + 1)
        )
    return torch.stack(polynomials)


def perspective_basis(analytic_variance: Tensor, valid: Tensor) -> Tensor:
    """``(2, H, W)`` float64: a constant and ``log analytic_variance`` centred over ``valid`` (0 outside ``valid``).

    With coefficients ``(c0, c1)`` the model is ``sigma^2 = exp(c0) (analytic_variance / g)^c1`` (``g`` the geometric
    mean of ``analytic_variance`` over ``valid``): the analytic shape (``c1 = 1``) scaled by a learned noise power, or
    bent.
    """
    log_analytic = torch.where(valid, analytic_variance.to(torch.float64), 1.0).log()
    centred = log_analytic - log_analytic[valid].mean()
    return torch.stack([torch.ones_like(centred), torch.where(valid, centred, 0.0)])


def _center(center: tuple[float, float] | None, shape: tuple[int, int]) -> tuple[float, float]:
    if center is None:
        return (shape[0] - 1) / 2, (shape[1] - 1) / 2
    try:
        row0, col0 = (float(value) for value in center)
    except (TypeError, ValueError):
        raise ValueError(f"center must be (row, column), two finite numbers, got {center!r}") from None
    if not (math.isfinite(row0) and math.isfinite(col0)):
        raise ValueError(f"center must be (row, column), two finite numbers, got {center!r}")
    return row0, col0


class LearnedVariance(VarianceModel):
    """A per-pixel noise variance map fitted to local/prior residuals by maximum likelihood.

    Plug it into :class:`~enmi_torch.losses.ENMILoss` (``variance_model=...``): its :meth:`forward` gives the map
    ``(1, 1, H, W)`` and :meth:`valid_mask` the pixels it was learned on. Fit it by minimising :meth:`nll` (plus
    :meth:`penalty` for the smoothness prior) with any optimiser, as ``train/fit_mask.py`` does; save it with
    :meth:`save` and read it back with :meth:`load`.

    Args:
        shape: ``(H, W)`` of the images.
        form: ``"pixel"`` (a free log-variance per pixel), ``"radial"`` (a polynomial of degree ``degree`` in the
            distance from ``center``, in log space) or ``"perspective"`` (``exp(c0) (analytic_variance / g)^c1``, see
            :func:`perspective_basis`).
        init_variance: the variance every valid pixel starts from (> 0).
        valid: bool ``(H, W)`` map of the pixels to learn; ``None`` for all. Others are never learned and are left
            out by :class:`~enmi_torch.losses.ENMILoss`.
        degree: degree of the radial polynomial (``form="radial"``).
        center: ``(row, column)`` of the vehicle for ``form="radial"``; default the image centre.
        analytic_variance: positive ``(H, W)`` analytic map (``form="perspective"`` only), finite and > 0 where valid.
        smoothness: precision ``lambda >= 0`` of the smoothness prior
            ``lambda/2 sum (s_p - s_q)^2`` (:func:`smoothness_penalty`), in units of the summed log-likelihood of all
            pairs: its weight relative to the data falls as pairs are added.

    Convention:
        Parameters are float32 unless the module is converted (``.double()``); :meth:`forward` returns the
        ``captured`` dtype. Gradients flow to the parameters through :meth:`forward`, :meth:`nll` and
        :meth:`penalty`.

    Example:
        >>> model = LearnedVariance((4, 4), init_variance=2.0)
        >>> model(torch.zeros(3, 1, 4, 4)).shape
        torch.Size([1, 1, 4, 4])
        >>> round(model(torch.zeros(1, 1, 4, 4))[0, 0, 0, 0].item(), 4)
        2.0
    """

    def __init__(
        self,
        shape: tuple[int, int],
        form: str = "pixel",
        *,
        init_variance: float = 1.0,
        valid: Tensor | None = None,
        degree: int = 4,
        center: tuple[float, float] | None = None,
        analytic_variance: Tensor | None = None,
        smoothness: float = 0.0,
    ) -> None:
        super().__init__()
        self.shape = check_image_shape("shape", shape)
        self.form = check_option("form", form, FORMS)
        self.degree = check_non_negative_int("degree", degree)
        # float32 maps per pixel: the log-variance (or the radial basis, degree + 1 planes, or the analytic map and its
        # two basis planes), the variance map forward() returns, and the bool valid map.
        planes = {"pixel": 2, "radial": self.degree + 2, "perspective": 4}[self.form]
        check_cells_memory(
            f"shape={shape!r}",
            self.shape[0] * self.shape[1],
            4 * planes + 1,
            f"{planes} float32 map(s) and a bool mask of {self.shape[0]} x {self.shape[1]}",
            "pass a smaller shape",
        )
        self.center = _center(center, self.shape)
        if isinstance(smoothness, bool) or not isinstance(smoothness, (int, float)) or not smoothness >= 0:
            raise ValueError(f"smoothness must be a finite number >= 0, got {smoothness!r}")
        if not math.isfinite(smoothness):
            raise ValueError(f"smoothness must be a finite number >= 0, got {smoothness!r}")
        self.smoothness = float(smoothness)
        self.register_buffer("valid", self._check_valid(valid))
        if form == "perspective":
            self.register_buffer("analytic_variance", self._check_analytic_variance(analytic_variance))
            basis = perspective_basis(self.analytic_variance, self.valid)
        elif analytic_variance is not None:
            raise ValueError(f"analytic_variance is only used by form='perspective', got form={form!r}")
        else:
            basis = radial_basis(self.shape, self.degree, self.center) if form == "radial" else None
        if basis is None:
            self.log_variance = nn.Parameter(torch.zeros(self.shape))
        else:
            self.register_buffer("basis", basis.float(), persistent=False)
            self.coefficients = nn.Parameter(torch.zeros(basis.shape[0]))
        self.reset_parameters(init_variance)

    def _check_valid(self, valid: Tensor | None) -> Tensor:
        if valid is None:
            return torch.ones(self.shape, dtype=torch.bool)
        check_tensor("valid", valid)
        if valid.dtype != torch.bool or tuple(valid.shape) != self.shape:
            raise ValueError(f"valid must be a bool map of shape {self.shape}, got {valid.dtype} {tuple(valid.shape)}")
        if not bool(valid.any()):
            raise ValueError("valid must select at least one pixel, got an all-False map")
        return valid.detach().clone().cpu()

    def _check_analytic_variance(self, analytic_variance: Tensor | None) -> Tensor:
        if analytic_variance is None:
            raise ValueError("form='perspective' needs analytic_variance, a positive (H, W) variance map, got None")
        check_floating("analytic_variance", analytic_variance)
        if tuple(analytic_variance.shape) != self.shape:
            raise ValueError(f"analytic_variance must have shape {self.shape}, got {tuple(analytic_variance.shape)}")
        analytic_variance = analytic_variance.detach().to(torch.float64).cpu()
        bad = self.valid & ~(torch.isfinite(analytic_variance) & (analytic_variance > 0))
        if bool(bad.any()):
            raise ValueError(
                f"analytic_variance must be finite and > 0 where valid, got {int(bad.sum())} pixel(s) outside that"
            )
        return torch.where(self.valid, analytic_variance, 1.0)

    @torch.no_grad()
    def reset_parameters(self, init_variance: float = 1.0) -> None:
        """Start again from ``init_variance`` everywhere (``"perspective"``: the analytic map's shape at that level)."""
        log_init = math.log(check_positive_number("init_variance", init_variance))
        if self.form == "pixel":
            self.log_variance.fill_(log_init)
            return
        self.coefficients.zero_()
        self.coefficients[0] = log_init
        if self.form == "perspective":
            self.coefficients[1] = 1.0

    @torch.no_grad()
    def set_valid(self, valid: Tensor) -> None:
        """Replace the valid map, e.g. by the pixels observed often enough; call it before fitting.

        For ``form="perspective"`` the new map must lie within the one the analytic map was given for, and the basis
        is centred again over it (which shifts the meaning of ``c0``).
        """
        valid = self._check_valid(valid).to(self.valid.device)
        if self.form == "perspective":
            if bool((valid & ~self.valid).any()):
                raise ValueError("valid must lie within the pixels where analytic_variance is defined")
            self.basis.copy_(perspective_basis(self.analytic_variance, valid).to(self.basis))
        self.valid.copy_(valid)

    def log_variance_map(self) -> Tensor:
        """``log sigma^2``, ``(H, W)``, with gradient to the parameters."""
        if self.form == "pixel":
            return self.log_variance
        return torch.einsum("k,khw->hw", self.coefficients, self.basis.to(self.coefficients.dtype))

    def variance_map(self) -> Tensor:
        """The variance ``(H, W)`` in float64, NaN outside :attr:`valid`, without gradient (for export and plots)."""
        with torch.no_grad():
            variance = self.log_variance_map().detach().to(torch.float64).exp()
        return torch.where(self.valid, variance, torch.nan)

    def forward(self, captured: Tensor) -> Tensor:
        """Variance ``(1, 1, H, W)`` in the dtype of ``captured`` ``(B, 1, H, W)``."""
        check_floating("captured", captured)
        self._check_images("captured", captured)
        return self.log_variance_map().exp().to(captured.dtype)[None, None]

    def valid_mask(self, captured: Tensor) -> Tensor:
        """Bool ``(1, 1, H, W)`` map of the learned pixels."""
        self._check_images("captured", captured)
        return self.valid.to(captured.device)[None, None]

    def nll(
        self, captured: Tensor, reference: Tensor, valid_mask: Tensor | None = None, *, reduction: str = "mean"
    ) -> Tensor:
        """:func:`gaussian_nll` of ``captured - reference`` ``(B, 1, H, W)`` on the pixels valid for mask and model."""
        check_floating("captured", captured)
        check_floating("reference", reference)
        if reference.shape != captured.shape:
            raise ValueError(
                f"reference must have the shape of captured {tuple(captured.shape)}, got {tuple(reference.shape)}"
            )
        self._check_images("captured", captured)
        check_not_empty("captured", captured)
        valid = self.valid_mask(captured)
        if valid_mask is not None:
            mask = mask_map("valid_mask", valid_mask, captured, "captured", require_pixels=False)
            valid = mask.reshape(-1, 1, *self.shape) & valid
        return gaussian_nll(captured - reference, self.log_variance_map(), valid, reduction=reduction)

    def penalty(self) -> Tensor:
        """``smoothness * smoothness_penalty(log sigma^2, valid)``: the negative log-prior, a scalar."""
        return self.smoothness * smoothness_penalty(self.log_variance_map(), self.valid)

    def _check_images(self, name: str, images: Tensor) -> None:
        if images.ndim not in (3, 4) or tuple(images.shape[-2:]) != self.shape:
            raise ValueError(
                f"{name} must have shape (B, 1, H, W) with (H, W) = {self.shape}, got {tuple(images.shape)}"
            )

    def extra_repr(self) -> str:
        """Shape, form and smoothness in the module's repr."""
        return f"shape={self.shape}, form={self.form!r}, smoothness={self.smoothness}"

    def save(self, path: str | Path) -> Path:
        """Write the model to ``path``: ``.pt`` (form and parameters) or ``.npy`` (the variance map, NaN invalid).

        The ``.pt`` file holds only a plain dict of tensors, strings and numbers, so that :meth:`load` reads it with
        ``torch.load(..., weights_only=True)``; the ``.npy`` file holds a float32 ``(H, W)`` array and no pickle.
        """
        path = check_file_to_write(path, "path")
        suffix = _check_suffix(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if suffix == ".npy":
            np.save(path, self.variance_map().float().numpy(), allow_pickle=False)
            return path
        config = {
            "shape": list(self.shape),
            "form": self.form,
            "degree": self.degree,
            "center": list(self.center),
            "smoothness": self.smoothness,
        }
        state = {name: value.detach().cpu().clone() for name, value in self.state_dict().items()}
        torch.save({"format": FILE_FORMAT, "version": FILE_VERSION, "config": config, "state": state}, path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> LearnedVariance:
        """Read a model written by :meth:`save`; refuses anything else (pickled objects included) with ``ValueError``.

        A ``.npy`` map gives a ``form="pixel"`` model valid where the map is finite.
        """
        path = Path(path)
        suffix = _check_suffix(path)
        if not path.is_file():
            raise FileNotFoundError(f"no variance mask file at {path}")
        if suffix == ".npy":
            return cls._load_npy(path)
        return cls._from_payload(path, load_plain_torch(path, "a plain tensor file"))

    @classmethod
    def _load_npy(cls, path: Path) -> LearnedVariance:
        variance = read_npy(path, "path")
        if variance.ndim != 2 or variance.dtype.kind != "f":
            raise ValueError(f"{path} must hold a floating (H, W) variance map, got {variance.dtype} {variance.shape}")
        valid = np.isfinite(variance)
        if np.isinf(variance).any() or (variance[valid] <= 0).any() or not valid.any():
            raise ValueError(
                f"{path} must hold values > 0 where valid and NaN elsewhere, with one valid pixel at least"
            )
        model = cls(tuple(int(size) for size in variance.shape), valid=torch.from_numpy(valid))
        with torch.no_grad():
            model.log_variance.copy_(torch.from_numpy(np.where(valid, variance, 1.0)).log())
        return model

    @classmethod
    def _from_payload(cls, path: Path, payload: object) -> LearnedVariance:
        def refuse(reason: str) -> ValueError:
            return ValueError(f"{path} is refused: not a {FILE_FORMAT} file ({reason})")

        if not isinstance(payload, dict) or set(payload) != {"format", "version", "config", "state"}:
            raise refuse("expected a dict with keys format, version, config, state")
        if payload["format"] != FILE_FORMAT or payload["version"] != FILE_VERSION:
            raise refuse(f"format {payload['format']!r} version {payload['version']!r}")
        config, state = payload["config"], payload["state"]
        if not isinstance(config, dict) or set(config) != {"shape", "form", "degree", "center", "smoothness"}:
            raise refuse("config must have keys shape, form, degree, center, smoothness")
        if not isinstance(state, dict) or not all(isinstance(value, Tensor) for value in state.values()):
            raise refuse("state must be a dict of tensors")
        if "reference" in state:  # files written before the analytic map's buffer was renamed
            state = {("analytic_variance" if name == "reference" else name): value for name, value in state.items()}
        # Sizes from the shapes alone: a stride-0 tensor of a few bytes on disk can claim gigabytes once copied.
        stored = sum(value.shape.numel() * value.element_size() for value in state.values())
        if not within_budget(stored):
            shapes = ", ".join(f"{name} {tuple(value.shape)}" for name, value in state.items())
            raise budget_error(stored, str(path), f"the tensors of its state ({shapes})", "check the file")
        valid = state.get("valid")
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool:
            raise refuse("state['valid'] must be a bool tensor")
        try:
            model = cls(
                tuple(config["shape"]),
                config["form"],
                valid=valid,
                degree=config["degree"],
                center=tuple(config["center"]),
                analytic_variance=state.get("analytic_variance"),
                smoothness=config["smoothness"],
            )
        except MemoryBudgetError as error:
            raise MemoryBudgetError(f"{path}: {error}") from None
        except (TypeError, ValueError) as error:
            raise refuse(str(error)) from None
        expected = model.state_dict()
        if set(state) != set(expected):
            raise refuse(f"state keys {sorted(state)}, expected {sorted(expected)}")
        for name, value in state.items():
            same_kind = value.is_floating_point() == expected[name].is_floating_point()
            if (
                value.shape != expected[name].shape
                or not same_kind
                or (value.dtype == torch.bool) != (expected[name].dtype == torch.bool)
            ):
                raise refuse(
                    f"state[{name!r}] is {value.dtype} {tuple(value.shape)}, "
                    f"expected {expected[name].dtype} {tuple(expected[name].shape)}"
                )
            if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                raise refuse(f"state[{name!r}] holds NaN or inf")
        model.load_state_dict(state)
        return model


def _check_suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in (".pt", ".npy"):
        raise ValueError(f"path must end in .pt or .npy, got {str(path)!r}")
    return suffix
