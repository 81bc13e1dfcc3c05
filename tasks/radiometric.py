"""Radiometric calibration of an ingest: LED gains from a white-standard BTF store, colour matrix.

An acquisition engineer captures the white standard on the dome like any
sample (``btf simulate --classes white-standard`` does it on the virtual
dome), ingests it uncalibrated (``btf ingest WHITE --out WHITE_BTF``), and
then ingests every material with ``--white WHITE_BTF``: each view's textures
are divided by the LED gains (:func:`btfcore.capture.radiometric.apply_led_calibration`)
and, with ``--colour-matrix``, mapped by the camera's colour matrix.

The gains are estimated out of core, one view chunk of the white store at a
time: :func:`btfcore.capture.radiometric.led_calibration` (a median over the view's
texels) per view, then the median over views. The median of per-view
medians is not the median over all samples, but it is as robust (a bad view
or a few bad texels do not move it) and needs one chunk in memory.

In the same pass the store is checked to be a white standard at all
(:func:`btfcore.capture.radiometric.white_texture_statistics`): flat in brightness
and chromaticity under every LED, of one colour under an LED from every
view. A store that is not (a leather BTF given as ``--white``) is refused
before its gains calibrate anything (:data:`btfcore.capture.radiometric.WHITE_TOLERANCES`).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from btfcore.capture.radiometric import (
    as_colour_matrix,
    led_calibration,
    white_standard_problems,
    white_standard_statistics,
    white_texture_statistics,
)
from tasks.stores.btf import BtfStore, open_btf_store

WHITE_ALBEDO = 0.99


#: Units of a BTF whose LED gains were divided out (``btf ingest`` / ``btf reconstruct`` with ``--white``).
CALIBRATED_UNITS = "radiance relative to a unit-irradiance white light (white-standard calibrated)"


@dataclass(frozen=True)
class Calibration:
    """What ``btf ingest`` applies after demultiplexing.

    Attributes
    ----------
    led_gain : (n_leds, 3) ndarray of float64 or None
        Per-LED RGB gain (DN/s of a unit-irradiance white light).
    colour_matrix : (3, 3) or (3, 4) ndarray of float64 or None
        Camera RGB -> target RGB.
    info : dict
        Provenance written to the BTF store's ``radiometric`` attribute.
    """

    led_gain: np.ndarray | None = None
    colour_matrix: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)

    def key(self) -> str:
        """Hash of the arrays, part of the ingest's resumption key."""
        h = hashlib.sha256()
        for a in (self.led_gain, self.colour_matrix):
            h.update(b"-" if a is None else np.ascontiguousarray(a, dtype=np.float64).tobytes())
        return h.hexdigest()[:16]


def _open_white(path: str | os.PathLike) -> BtfStore:
    if not Path(path).exists():
        raise FileNotFoundError(f"{path}: no white-standard BTF store there; ingest the white-standard capture "
                                "first (btf ingest WHITE_CAPTURE --out WHITE_BTF)")
    store = open_btf_store(path, require_complete=False, produced_by="`btf ingest`",
                           ingested_only="give the ingested white standard")
    if not store.complete:
        raise ValueError(f"{path}: the white standard's ingest is unfinished (attribute complete = false); "
                         "run `btf ingest` on it again to finish it")
    if store.attrs.get("radiometric"):
        raise ValueError(f"{path}: this BTF store is already radiometrically corrected; calibrate from an "
                         "uncorrected ingest of the white standard (without --white)")
    return store


def led_gains_from_white(white_path: str | os.PathLike, albedo: float = WHITE_ALBEDO) -> tuple[np.ndarray, dict]:
    """Per-LED RGB gains from an ingested white standard, one view chunk at a time.

    Parameters
    ----------
    white_path : path
        ``btf-texture`` store of a white-standard capture, not corrected.
    albedo : float
        The standard's albedo.

    Returns
    -------
    gain : (n_leds, 3) ndarray of float64
        Median over views of :func:`btfcore.capture.radiometric.led_calibration`.
    info : dict
        Provenance: the store, its ingest hash, the albedo, the number of
        views, the largest relative spread of a gain across views and the
        white-standard statistics (``white_check``).

    Raises
    ------
    ValueError
        On a store that is not a finished, uncorrected ingest, (from
        ``led_calibration``) NaN/Inf, an LED below the horizon or a
        non-positive gain (the message names the store, the view and the
        LED), or a store that is not a white standard: a statistic of
        :func:`btfcore.capture.radiometric.white_standard_statistics` above its
        tolerance (the message names the store, the statistic, its value and
        the tolerance).
    """
    white = _open_white(white_path)
    n_turn, n_cam, n_leds = white.attrs["turntable_cameras_leds"]
    btf, light_dir = white.btf, white.light_dir
    n_views = n_turn * n_cam
    per_view = np.empty((n_views, n_leds, 3))
    spread, chroma_spread = np.empty((n_views, n_leds)), np.empty((n_views, n_leds))
    chromaticity = np.empty((n_views, n_leds, btf.shape[-1]))
    for v in range(n_views):
        rows = slice(v * n_leds, (v + 1) * n_leds)
        chunk = btf[rows]                                   # one view: the gains and the check in one read
        try:
            per_view[v] = led_calibration(chunk, light_dir[rows], albedo)
        except ValueError as exc:
            raise ValueError(f"{white_path}: btf rows {rows.start}-{rows.stop - 1} (turntable {v // n_cam}, "
                             f"camera {v % n_cam}): {exc}; check that view's frames and dark frames, or capture "
                             "the white standard again with every LED lighting it") from None
        spread[v], chroma_spread[v], chromaticity[v] = white_texture_statistics(chunk)
    stats = white_standard_statistics(spread, chroma_spread, chromaticity)
    check_white_standard(white_path, stats)
    gain = np.median(per_view, axis=0)
    gain_spread = float(np.max(np.abs(per_view - gain) / gain))
    info = {"white_standard": str(white_path), "white_ingest_hash": white.attrs.get("ingest_hash"),
            "albedo": float(albedo), "views": int(n_views), "max_relative_spread_over_views": gain_spread,
            "white_check": {name: round(value, 6) for name, value in stats.items()}}
    return gain, info


_STATISTIC_WORDS = {
    "brightness_spread": "its texels are not equally bright under an LED",
    "chromaticity_spread": "its texels are not of one colour under an LED",
    "view_chromaticity_deviation": "the colour of an LED relative to the others changes with the view",
}


def check_white_standard(white_path: str | os.PathLike, stats: dict[str, float]) -> None:
    """Refuse a ``--white`` store whose statistics are not a white standard's.

    Parameters
    ----------
    white_path : path
        The store (named in the message).
    stats : dict
        From :func:`btfcore.capture.radiometric.white_standard_statistics`.

    Raises
    ------
    ValueError
        One line naming the store, each statistic above its tolerance of
        :data:`btfcore.capture.radiometric.WHITE_TOLERANCES` with its value, and what
        to give instead.
    """
    problems = white_standard_problems(stats)
    if problems:
        what = "; ".join(f"{name} = {value:.4g} > {tol:g} ({_STATISTIC_WORDS.get(name, name)})"
                         for name, value, tol in problems)
        raise ValueError(f"{white_path}: not a white standard: {what}; give --white the ingest of a white-standard "
                         "capture (a flat, neutral Lambertian target; docs/reconstruction.md, \"Is the white "
                         "standard a white standard?\")")


def read_colour_matrix(path: str | os.PathLike) -> np.ndarray:
    """A colour matrix from JSON: ``{"matrix": [[...], ...]}`` or the bare nested list, (3, 3) or (3, 4)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable colour-matrix JSON file ({exc})") from None
    matrix = data.get("matrix") if isinstance(data, dict) else data
    try:
        return as_colour_matrix(matrix)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: {exc}; write {{\"matrix\": [[r_r, r_g, r_b], [g_r, ...], [b_r, ...]]}}") from None


def load_calibration(white: str | os.PathLike | None = None, albedo: float = WHITE_ALBEDO,
                     colour_matrix: str | os.PathLike | None = None) -> Calibration | None:
    """The calibration of ``btf ingest --white ... --colour-matrix ...``; ``None`` when neither is given."""
    if white is None and colour_matrix is None:
        return None
    gain, info = (None, {}) if white is None else led_gains_from_white(white, albedo)
    matrix = None if colour_matrix is None else read_colour_matrix(colour_matrix)
    if matrix is not None:
        info = {**info, "colour_matrix": str(colour_matrix)}
    return Calibration(led_gain=gain, colour_matrix=matrix, info=info)
