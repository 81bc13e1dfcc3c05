"""The per-image super-resolution network of the SR paper (§4.2, eqs. (5)-(6)).

ESPCN after Shi et al. [1]_ with the skip connection of Tong et al. [2]_ and batch
norm, on one channel of an HDR radiance image (SR paper §4.2: :math:`n_0 = 1`; a colour
image is up-sampled one channel at a time, :func:`upscale_rgb`):

.. math::

    f_1 = \\phi(\\mathrm{BN}_1(W_1 * I_{LR} + b_1)), \\quad
    f_2 = \\phi(\\mathrm{BN}_2(W_2 * f_1 + b_2)), \\quad
    f_3 = \\phi(\\mathrm{BN}_3(W_3 * f_2 + b_3)),

.. math::

    I_{SR} = \\mathcal{PS}\\big(W_4 * (f_1; f_3) + b_4\\big),

with :math:`\\phi` = ReLU, kernels 5, 3, 3, 3, features 64, 32, 32, :math:`r^2`
(SR paper §5.2.2), :math:`(f_1; f_3)` the concatenation of 96 channels (eq. (6)) and
:math:`\\mathcal{PS}` the periodic shuffle to one channel at r times the size (eq. (5)).

Choices the paper leaves open (SR paper §4.2 says only that batch norm is used):

* batch norm after each of conv1-conv3, **before** the ReLU (Ioffe and Szegedy's
  placement); none after conv4, whose output is the image;
* 'same' padding by **reflection** (``EspcnConfig.padding='reflect'``): zero padding,
  Shi et al.'s, darkens the borders of a bright image; ``'zeros'`` is available;
* PyTorch's default initialisation; the convolutions keep their biases (eq. (5)), which
  batch norm makes redundant for conv1-conv3 but which cost nothing;
* HDR radiance is normalised per image before the network and the output mapped back
  with the low-resolution image's statistics (:func:`normalise`, :func:`denormalise`).

Inference (:func:`upscale`) runs the functional twin :func:`espcn_functional`, which
folds batch norm into the convolutions and computes conv1 and conv4 as GEMMs (oneDNN
is slow for one input channel and for r^2 output channels), one image per call by
default: on two cores it reached 54 % of the float32 GEMM rate on 144 x 144 images,
68 % on one core (the module's own forward: about 20 %).

References
----------
.. [1] W. Shi et al., "Real-time single image and video super-resolution using an
   efficient sub-pixel convolutional neural network", CVPR 2016.
.. [2] T. Tong, G. Li, X. Liu, Q. Gao, "Image super-resolution using dense skip
   connections", ICCV 2017.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "BN_EPS", "LOG_EPS_FRACTION", "NORMALISATIONS", "PADDINGS", "PIXELS_PER_BATCH", "SCALE_FLOOR",
    "Espcn", "EspcnConfig", "NormalisationStats", "conv_flops", "denormalise",
    "espcn_functional", "load_espcn", "normalise", "state_dict_problems", "upscale",
    "upscale_rgb",
]

#: Input normalisations of HDR radiance (:func:`normalise`).
NORMALISATIONS: tuple[str, ...] = ("log", "scale")
#: 'same' padding modes of the convolutions (``torch.nn.Conv2d`` names).
PADDINGS: tuple[str, ...] = ("reflect", "zeros", "replicate")
#: Epsilon of the batch norms (PyTorch's default), shared by the module and its twin.
BN_EPS = 1e-5
#: Floor of an image's scale :math:`s_i` (an all-zero image keeps a finite scale).
SCALE_FLOOR = 1e-12
#: :math:`\\delta` of the log normalisation: :math:`\\varepsilon_i = \\delta s_i`.
LOG_EPS_FRACTION = 1e-3
#: Low-resolution pixels per inference batch when ``upscale(batch=None)``: one 144 x 144
#: image's activations stay in cache-friendly sizes; 16 images per call ran at 60 % of
#: the speed of one on two cores (fresh large buffers are first-touched every call).
PIXELS_PER_BATCH = 1 << 15


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class EspcnConfig:
    """Architecture and input normalisation of an :class:`Espcn`.

    Parameters
    ----------
    scale : int
        Up-sampling factor r >= 2 (SR paper §5.2.2: r = 2).
    features : (3,) tuple of int
        Output channels of conv1-conv3 (SR paper §5.2.2: 64, 32, 32); conv4 has r^2.
    kernels : (4,) tuple of int
        Odd kernel sizes of conv1-conv4 (SR paper §5.2.2: 5, 3, 3, 3).
    batch_norm : bool
        Batch norm after conv1-conv3, before the ReLU (SR paper §4.2).
    normalisation : {'scale', 'log'}
        Per-image input normalisation of HDR radiance (:func:`normalise`). ``'scale'`` by default: on
        the simulated leathers and cloths it measured better (docs/super-resolution.md, "Results");
        ``'log'`` amplifies the noise of dark pixels and diverged on cloth.
    padding : {'reflect', 'zeros', 'replicate'}
        'same' padding mode of every convolution.
    """

    scale: int = 2
    features: tuple[int, int, int] = (64, 32, 32)
    kernels: tuple[int, int, int, int] = (5, 3, 3, 3)
    batch_norm: bool = True
    normalisation: str = "scale"
    padding: str = "reflect"

    def __post_init__(self) -> None:
        object.__setattr__(self, "features", tuple(self.features))
        object.__setattr__(self, "kernels", tuple(self.kernels))
        problems = []
        if not _is_int(self.scale) or self.scale < 2:
            problems.append(f"scale must be an int >= 2, got {self.scale!r}")
        if len(self.features) != 3 or not all(_is_int(f) and f >= 1 for f in self.features):
            problems.append(f"features must be 3 positive ints (conv1-conv3), got {self.features!r}")
        if len(self.kernels) != 4 or not all(_is_int(k) and k >= 1 and k % 2 == 1
                                             for k in self.kernels):
            problems.append(f"kernels must be 4 odd positive ints (conv1-conv4), got {self.kernels!r}")
        if not isinstance(self.batch_norm, bool):
            problems.append(f"batch_norm must be a bool, got {self.batch_norm!r}")
        if self.normalisation not in NORMALISATIONS:
            problems.append(f"normalisation must be one of {NORMALISATIONS}, got {self.normalisation!r}")
        if self.padding not in PADDINGS:
            problems.append(f"padding must be one of {PADDINGS}, got {self.padding!r}")
        if problems:
            raise ValueError("invalid EspcnConfig: " + "; ".join(problems))

    @property
    def min_size(self) -> int:
        """Smallest input height and width: reflection needs more pixels than it pads."""
        return max(self.kernels) // 2 + 1

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON dict; :meth:`from_json` inverts it."""
        d = dataclasses.asdict(self)
        d["features"] = list(self.features)
        d["kernels"] = list(self.kernels)
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "EspcnConfig":
        """Inverse of :meth:`to_json`; refuses unknown keys (a file of another architecture)."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown EspcnConfig key(s) {unknown}; known keys are {sorted(known)}")
        return cls(**dict(d))


def _is_int(x: Any) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def conv_flops(config: EspcnConfig, n_pixels: int) -> int:
    """Floating-point operations of the four convolutions on ``n_pixels`` input pixels.

    2 x the multiply-adds: :math:`\\sum_l n_{l-1} n_l k_l^2` per low-resolution pixel
    (conv4 has :math:`n_1 + n_3` inputs, eq. (6)).
    """
    f1, f2, f3 = config.features
    k1, k2, k3, k4 = config.kernels
    macs = 1 * f1 * k1 ** 2 + f1 * f2 * k2 ** 2 + f2 * f3 * k3 ** 2 + (f1 + f3) * config.scale ** 2 * k4 ** 2
    return 2 * macs * int(n_pixels)


# --------------------------------------------------------------------------- the network


class Espcn(nn.Module):
    """ESPCN with the skip of eq. (6) and batch norm (SR paper §4.2), see the module docstring.

    Parameters
    ----------
    config : EspcnConfig, optional
        Architecture; the paper's by default.

    Notes
    -----
    ``forward`` maps normalised (N, 1, H, W) to (N, 1, rH, rW), float32; use
    :func:`upscale` for numpy HDR images.
    """

    def __init__(self, config: EspcnConfig | None = None) -> None:
        super().__init__()
        self.config = config = EspcnConfig() if config is None else config
        f1, f2, f3 = config.features
        k1, k2, k3, k4 = config.kernels
        r = config.scale

        def conv(n_in: int, n_out: int, k: int) -> nn.Conv2d:
            return nn.Conv2d(n_in, n_out, k, padding=k // 2, padding_mode=config.padding)

        self.conv1, self.conv2 = conv(1, f1, k1), conv(f1, f2, k2)
        self.conv3, self.conv4 = conv(f2, f3, k3), conv(f1 + f3, r * r, k4)
        norm = (lambda n: nn.BatchNorm2d(n, eps=BN_EPS)) if config.batch_norm else (lambda n: nn.Identity())
        self.bn1, self.bn2, self.bn3 = norm(f1), norm(f2), norm(f3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 1, H, W) normalised images -> (N, 1, rH, rW)."""
        _check_input(x, self.config)
        f1 = F.relu(self.bn1(self.conv1(x)))
        f3 = F.relu(self.bn3(self.conv3(F.relu(self.bn2(self.conv2(f1))))))
        return F.pixel_shuffle(self.conv4(torch.cat((f1, f3), dim=1)), self.config.scale)


def _check_input(x: torch.Tensor, config: EspcnConfig) -> None:
    if x.ndim != 4:
        hint = " (add the channel axis: x[:, None])" if x.ndim == 3 else ""
        raise ValueError(f"ESPCN input must be (N, 1, H, W), got a {x.ndim}-D shape {tuple(x.shape)}{hint}")
    if x.shape[1] != 1:
        raise ValueError(f"ESPCN input must have 1 channel (SR paper §4.2: n_0 = 1), got {x.shape[1]} "
                         f"in shape {tuple(x.shape)}; up-sample colour one channel at a time (upscale_rgb)")
    if min(x.shape[2:]) < config.min_size:
        raise ValueError(f"ESPCN input of {x.shape[2]} x {x.shape[3]} pixels is smaller than the "
                         f"{config.min_size} x {config.min_size} its padding needs")
    if not x.is_floating_point():
        raise ValueError(f"ESPCN input must be floating point, got {x.dtype}")


def _folded(state: Mapping[str, torch.Tensor], config: EspcnConfig, layer: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights and bias of conv ``layer`` with its eval-mode batch norm folded in.

    :math:`\\mathrm{BN}(W * x + b) = (\\gamma / \\sigma) W * x + (b - m) \\gamma / \\sigma + \\beta`
    with :math:`\\sigma = \\sqrt{v + \\epsilon}` (running mean m and variance v).
    """
    w, b = state[f"conv{layer}.weight"], state[f"conv{layer}.bias"]
    if config.batch_norm and layer < 4:
        g = state[f"bn{layer}.weight"] / torch.sqrt(state[f"bn{layer}.running_var"] + BN_EPS)
        w = w * g[:, None, None, None]
        b = (b - state[f"bn{layer}.running_mean"]) * g + state[f"bn{layer}.bias"]
    return w, b


def _pad(x: torch.Tensor, p: int, mode: str) -> torch.Tensor:
    """'same' padding of (B, C, H, W) by ``p`` pixels in ``mode`` (``F.pad``, any layout)."""
    return F.pad(x, (p, p, p, p), mode="constant" if mode == "zeros" else mode) if p else x


def _pad_channels_last(x: torch.Tensor, p: int, mode: str) -> torch.Tensor:
    """Reflect or replicate padding of (N, C, H, W) into a channels-last buffer.

    ``F.pad`` of a channels-last map is a slow gather; this copies the map once into
    the interior of an (N, H + 2p, W + 2p, C) buffer and fills the p-pixel rim from it.
    """
    n, c, h, w = x.shape
    out = x.new_empty((n, h + 2 * p, w + 2 * p, c))
    out[:, p:p + h, p:p + w] = x.permute(0, 2, 3, 1)
    reflect = mode == "reflect"
    for k in range(1, p + 1):                                        # rows, then columns with corners
        top, bottom = (p + k, p + h - 1 - k) if reflect else (p, p + h - 1)
        out[:, p - k, p:p + w] = out[:, top, p:p + w]
        out[:, p + h - 1 + k, p:p + w] = out[:, bottom, p:p + w]
    for k in range(1, p + 1):
        left, right = (p + k, p + w - 1 - k) if reflect else (p, p + w - 1)
        out[:, :, p - k] = out[:, :, left]
        out[:, :, p + w - 1 + k] = out[:, :, right]
    return out.permute(0, 3, 1, 2)


def _conv_relu(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor, mode: str) -> torch.Tensor:
    """ReLU of a 'same' convolution (channels-last in and out, oneDNN's fast layout)."""
    p = w.shape[-1] // 2
    w = w.contiguous(memory_format=torch.channels_last)
    if mode == "zeros" or p == 0:
        return F.conv2d(x, w, b, padding=p).relu_()
    return F.conv2d(_pad_channels_last(x, p, mode), w, b).relu_()


def espcn_functional(state: Mapping[str, torch.Tensor], x: torch.Tensor,
                     config: EspcnConfig) -> torch.Tensor:
    """The functional twin of :class:`Espcn` in eval mode, arranged for inference speed.

    The same function as ``Espcn(config).eval()`` with the weights ``state`` (equal up
    to float rounding), computed as:

    * batch norm folded into conv1-conv3 (:func:`_folded`);
    * conv1 (one input channel) as one GEMM of the (N H W, k_1^2) patch matrix, whose
      (N H W, n_1) result is already channels-last;
    * conv2, conv3 by oneDNN on channels-last maps;
    * conv4 on the concatenation (eq. (6)) as two GEMMs, one per part, of 1 x 1 maps
      to (k_4^2 r^2) tap channels, padded and summed over the k_4^2 shifted taps
      (a pointwise map commutes with the padding), then the periodic shuffle (eq. (5)).

    Parameters
    ----------
    state : mapping of str to Tensor
        ``Espcn(config).state_dict()`` (checked by :func:`state_dict_problems`), on
        the device and of the dtype of ``x``.
    x : (N, 1, H, W) Tensor
        Normalised images.
    config : EspcnConfig

    Returns
    -------
    (N, 1, rH, rW) Tensor
    """
    problems = state_dict_problems(state, config)
    if problems:
        raise ValueError("state dict does not fit the ESPCN configuration: " + "; ".join(problems))
    _check_input(x, config)
    return _eval_forward(state, x, config)


def _eval_forward(state: Mapping[str, torch.Tensor], x: torch.Tensor, config: EspcnConfig) -> torch.Tensor:
    """:func:`espcn_functional` without its checks."""
    n, _, h, w = x.shape
    k1, k4 = config.kernels[0], config.kernels[3]
    r2 = config.scale ** 2
    w1, b1 = _folded(state, config, 1)
    patches = _pad(x, k1 // 2, config.padding)[:, 0].unfold(1, k1, 1).unfold(2, k1, 1)
    f1_rows = torch.addmm(b1, patches.reshape(n * h * w, k1 * k1), w1.reshape(len(b1), -1).T).relu_()
    f1 = f1_rows.view(n, h, w, -1).permute(0, 3, 1, 2)              # (N, n_1, H, W), channels last
    f3 = _conv_relu(_conv_relu(f1, *_folded(state, config, 2), config.padding),
                    *_folded(state, config, 3), config.padding)
    f3_rows = f3.permute(0, 2, 3, 1).reshape(n * h * w, -1)          # a view when channels last
    w4, b4 = _folded(state, config, 4)
    taps = w4.permute(2, 3, 0, 1).reshape(k4 * k4 * r2, -1)          # row (i k_4 + j) r^2 + o
    n1 = f1_rows.shape[1]
    y = torch.mm(taps[:, :n1], f1_rows.T).addmm_(taps[:, n1:], f3_rows.T)
    p = k4 // 2
    y = _pad(y.view(k4 * k4 * r2, n, h, w), p, config.padding).view(k4 * k4, r2, n, h + 2 * p, w + 2 * p)
    out = y[0, :, :, :h, :w] + b4[:, None, None, None]
    for tap in range(1, k4 * k4):
        i, j = divmod(tap, k4)
        out += y[tap, :, :, i:i + h, j:j + w]
    return F.pixel_shuffle(out.permute(1, 0, 2, 3), config.scale)


def state_dict_problems(state: Mapping[str, Any], config: EspcnConfig) -> list[str]:
    """What keeps ``state`` from loading into ``Espcn(config)``: missing, unexpected, reshaped.

    Returns
    -------
    list of str
        One line per problem; empty when the state fits.
    """
    with torch.device("meta"):                                       # shapes only: no RNG, no memory
        expected = {k: tuple(v.shape) for k, v in Espcn(config).state_dict().items()}
    problems = []
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing:
        problems.append(f"missing {missing}")
    if unexpected:
        problems.append(f"unexpected {unexpected}")
    for k in sorted(set(expected) & set(state)):
        v = state[k]
        if not isinstance(v, torch.Tensor):
            problems.append(f"{k} is a {type(v).__name__}, not a tensor")
        elif tuple(v.shape) != expected[k]:
            problems.append(f"{k} has shape {tuple(v.shape)}, the configuration needs {expected[k]}")
        elif v.is_floating_point() and not bool(torch.isfinite(v).all()):
            problems.append(f"{k} holds NaN or Inf")
    return problems


def load_espcn(state: Mapping[str, torch.Tensor], config: EspcnConfig) -> Espcn:
    """An :class:`Espcn` of ``config`` with the weights ``state``, in eval mode.

    Raises
    ------
    ValueError
        Listing every way ``state`` does not fit ``config`` (another architecture or scale).
    """
    problems = state_dict_problems(state, config)
    if problems:
        raise ValueError("state dict does not fit the ESPCN configuration: " + "; ".join(problems))
    model = Espcn(config)
    model.load_state_dict(dict(state))
    return model.eval()


# --------------------------------------------------------------------------- HDR normalisation


@dataclass(frozen=True)
class NormalisationStats:
    """Per-image statistics of :func:`normalise`, reused for the image's HR partner.

    Attributes
    ----------
    method : {'log', 'scale'}
    scale : (n,) float64 ndarray
        :math:`s_i = \\max(\\operatorname{mean}|x_i|, s_{min})`.
    log_mean : (n,) float64 ndarray
        :math:`\\mu_i`, the mean of the log image ('log'); zeros for 'scale'.
    """

    method: str
    scale: np.ndarray
    log_mean: np.ndarray

    def __len__(self) -> int:
        return len(self.scale)

    def __getitem__(self, index: Any) -> "NormalisationStats":
        """The statistics of a subset of the images (a slice or index array)."""
        return NormalisationStats(self.method, np.atleast_1d(self.scale[index]),
                                  np.atleast_1d(self.log_mean[index]))


def _finite_images(images: Any, name: str) -> np.ndarray:
    x = np.asarray(images)
    if x.ndim != 3:
        raise ValueError(f"{name} must be (n, H, W), got shape {x.shape}")
    if not np.issubdtype(x.dtype, np.floating) and not np.issubdtype(x.dtype, np.integer):
        raise ValueError(f"{name} must be real numbers, got dtype {x.dtype}")
    bad = ~np.isfinite(x).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"{name} hold NaN or Inf in {int(bad.sum())} image(s), the first at index "
                         f"{int(np.flatnonzero(bad)[0])}; mask or repair them before super-resolution")
    return x


def _per_image(v: np.ndarray, ndim: int) -> np.ndarray:
    return v.reshape((-1,) + (1,) * (ndim - 1))


def normalise(images: np.ndarray, method: str,
              stats: NormalisationStats | None = None) -> tuple[np.ndarray, NormalisationStats]:
    """Per-image normalisation of HDR radiance for the network (the SR paper does not state one).

    With :math:`s_i = \\max(\\operatorname{mean}|x_i|, s_{min})` (``SCALE_FLOOR``) and
    :math:`\\varepsilon_i = \\delta s_i` (``LOG_EPS_FRACTION``):

    * ``'scale'``: :math:`y = x / s_i`;
    * ``'log'``: :math:`y = \\log(\\max(x, 0) + \\varepsilon_i) - \\mu_i`, with
      :math:`\\mu_i` the mean of :math:`\\log(\\max(x_i, 0) + \\varepsilon_i)` over the
      image, so the network sees zero-centred inputs at any exposure.

    Parameters
    ----------
    images : (n, H, W) array_like
        Finite HDR radiance, one channel.
    method : {'log', 'scale'}
    stats : NormalisationStats, optional
        Statistics of another image set of the same length (an HR image is normalised
        with its LR image's); computed from ``images`` when omitted.

    Returns
    -------
    normalised : (n, H, W) float32 ndarray
    stats : NormalisationStats
        What :func:`denormalise` needs.
    """
    if method not in NORMALISATIONS:
        raise ValueError(f"normalisation must be one of {NORMALISATIONS}, got {method!r}")
    x = _finite_images(images, "images").astype(np.float64, copy=False)
    if stats is None:
        scale = np.maximum(np.abs(x).mean(axis=(1, 2)), SCALE_FLOOR) if len(x) else np.zeros(0)
        log_mean = np.zeros_like(scale)
        if method == "log" and len(x):
            log_mean = np.log(np.maximum(x, 0.0) + _per_image(LOG_EPS_FRACTION * scale, 3)).mean(axis=(1, 2))
        stats = NormalisationStats(method, scale, log_mean)
    elif stats.method != method:
        raise ValueError(f"stats were computed for normalisation {stats.method!r}, not {method!r}")
    elif len(stats) != len(x):
        raise ValueError(f"stats are of {len(stats)} images but there are {len(x)} images")
    s = _per_image(stats.scale, 3)
    if method == "scale":
        y = x / s
    else:
        y = np.log(np.maximum(x, 0.0) + LOG_EPS_FRACTION * s) - _per_image(stats.log_mean, 3)
    return y.astype(np.float32), stats


def denormalise(y: np.ndarray, stats: NormalisationStats, method: str) -> np.ndarray:
    """Inverse of :func:`normalise` with the given statistics (of the LR image for its SR output).

    * ``'scale'``: :math:`x = s_i y`;
    * ``'log'``: :math:`x = \\exp(y + \\mu_i) - \\varepsilon_i` (exact for non-negative
      radiance; :func:`normalise` clips negative values to 0).

    Parameters
    ----------
    y : (n, H', W') array_like
        Normalised images of any size (H', W' need not be the statistics' image size).
    stats : NormalisationStats
        Of ``n`` images.
    method : {'log', 'scale'}

    Returns
    -------
    (n, H', W') float32 ndarray
    """
    if stats.method != method:
        raise ValueError(f"stats were computed for normalisation {stats.method!r}, not {method!r}")
    y = np.asarray(y, dtype=np.float64)
    if y.ndim < 1 or len(y) != len(stats):
        raise ValueError(f"y has {len(y) if y.ndim else 0} images but stats are of {len(stats)}")
    s = _per_image(stats.scale, y.ndim)
    if method == "scale":
        x = y * s
    else:
        x = np.exp(y + _per_image(stats.log_mean, y.ndim)) - LOG_EPS_FRACTION * s
    return x.astype(np.float32)


# --------------------------------------------------------------------------- inference


def upscale(model: Espcn, images: np.ndarray, *, batch: int | None = None,
            device: str = "cpu") -> np.ndarray:
    """Up-sample HDR radiance images by the model's scale r.

    Normalises each image (``model.config.normalisation``), runs the network in eval
    mode (:func:`espcn_functional` on the model's weights, batch norm with its running
    statistics) under ``torch.no_grad()`` and maps the output back with the input
    image's statistics (:func:`denormalise`).

    Parameters
    ----------
    model : Espcn
        Left as it is (its weights are copied to ``device``).
    images : (n, H, W) array_like
        Finite radiance, one channel, any H, W >= ``model.config.min_size``.
    batch : int, optional
        Images per network call; by default as many as fit ``PIXELS_PER_BATCH``
        low-resolution pixels, at least one (a call peaks at about 0.7 kB per
        low-resolution pixel: 28 MB for a 200 x 200 region). Results of different
        batches differ only by float rounding (the GEMMs block differently).
    device : str
        ``'cpu'`` or ``'cuda'`` (a torch device string).

    Returns
    -------
    (n, rH, rW) float32 ndarray
    """
    config = model.config
    x = _finite_images(images, "images")
    n, h, w = x.shape
    r = config.scale
    if n and min(h, w) < config.min_size:
        raise ValueError(f"images of {h} x {w} pixels are smaller than the {config.min_size} x "
                         f"{config.min_size} the network's padding needs")
    if batch is None:
        batch = max(1, PIXELS_PER_BATCH // max(1, h * w))
    if not _is_int(batch) or batch < 1:
        raise ValueError(f"batch must be a positive int, got {batch!r}")
    out = np.empty((n, r * h, r * w), dtype=np.float32)
    state = {k: v.detach().to(device, torch.float32) for k, v in model.state_dict().items()}
    with torch.no_grad():
        for start in range(0, n, batch):
            y, stats = normalise(x[start:start + batch], config.normalisation)
            t = torch.from_numpy(y).to(device)[:, None]
            sr = _eval_forward(state, t, config)[:, 0].to("cpu", torch.float32).numpy()
            out[start:start + batch] = denormalise(sr, stats, config.normalisation)
    return out


def upscale_rgb(model: Espcn, images: np.ndarray, *, batch: int | None = None,
                device: str = "cpu") -> np.ndarray:
    """Up-sample colour images one channel at a time (SR paper §4.2: one input channel).

    Parameters
    ----------
    model, batch, device
        As :func:`upscale`.
    images : (n, H, W, C) array_like
        Channels last (C = 3 for RGB); each channel is normalised on its own.

    Returns
    -------
    (n, rH, rW, C) float32 ndarray
    """
    x = np.asarray(images)
    if x.ndim != 4:
        raise ValueError(f"images must be (n, H, W, C), got shape {x.shape}")
    n, h, w, c = x.shape
    planes = np.ascontiguousarray(np.moveaxis(x, -1, 1)).reshape(n * c, h, w)
    sr = upscale(model, planes, batch=batch, device=device)
    r = model.config.scale
    return np.ascontiguousarray(np.moveaxis(sr.reshape(n, c, r * h, r * w), 1, -1))
