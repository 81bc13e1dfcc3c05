"""Files this project writes, read by two readers it did not write (docs/bonn-formats.md, "Independent readers").

btf-extractor (PyPI; btf.hh's ``LoadBTF`` wrapped by Cython) and pysmtb (PyPI; ``read_ubo_btf_dfmf``)
need numpy < 2, so they live in their own venv (``make test`` builds ``.venv-readers``; the
``BTF_READERS_PYTHON`` environment variable names another python). ``bonn_readers.py`` runs there
and saves what a reader returns, raw; the quirks are undone here: btf.hh flips the texture rows
(y -> h-1-y) and returns BGR, clamps RGB to [0, 1] in colour model 11 and adds its eps after the
multiplication; pysmtb reads 3 floats per rotation instead of 9 (it works only with n_rot = 0).

Every file is written by ``tasks.bonn.dfmf.write_dfmf`` / ``write_fmf`` from seeded data with a
non-square texture (6 x 4, so an x/y mix-up shows) and n_l = n_v (btf.hh requires rows = n_l^2),
and decoded by our own reader (``read_factorised``, ``btfcore.bonn.decode_textures`` and
``decode_colour``); the values must agree within half-float precision of the magnitudes involved.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = Path(__file__).with_name("bonn_readers.py")
#: Unit roundoff of IEEE half floats: "half-float precision" of a value of magnitude m is HALF * m.
HALF = 2.0 ** -11
W, H = 6, 4
#: (theta, phi) degrees, UBO-like: multiples of 0.5 degree survive btf-extractor's rounding to 0.1.
VIEW_DEG = np.array([(0.0, 0.0), (30.0, 15.0), (52.5, 187.5), (75.0, 307.5)])
LIGHT_DEG = np.array([(11.0, 60.0), (37.5, 135.0), (60.0, 240.0), (75.0, 352.5)])
N_L = N_V = 4
N_LV, N_TX = N_L * N_V, W * H
YUV_TO_RGB = np.array([[1.0, 0.0, 1.13983], [1.0, -0.39465, -0.5806], [1.0, 2.03211, 0.0]])


# --- the readers' venv --------------------------------------------------------------------------

def readers_python() -> Path:
    """The python of the independent readers' venv (``BTF_READERS_PYTHON`` or ``.venv-readers``)."""
    return Path(os.environ.get("BTF_READERS_PYTHON") or ROOT / ".venv-readers" / "bin" / "python")


def last_error_line(log: Path) -> str:
    """The last line of a build log that reports an error (else its last line); '' without a log."""
    if not log.is_file():
        return ""
    lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
    errors = [line for line in lines if "error" in line.lower() and not line.startswith("FAILED to build")]
    return (errors or lines or [""])[-1]


@pytest.fixture(scope="module")
def readers() -> Path:
    """The readers' python; skips the module's cross-checks, with the reason, where it is absent or broken."""
    python = readers_python()
    venv = python.parent.parent
    log = Path(f"{venv}.log")
    if not python.exists():
        why = last_error_line(log)
        pytest.skip(f"no independent-reader venv at {venv}: "
                    + (f"its build failed ({log}: {why!r})" if why else "not built")
                    + "; `make readers` builds it (needs network to PyPI and a C++ compiler)")
    probe = subprocess.run([str(python), "-c", "import btf_extractor, pysmtb.btf"], capture_output=True,
                           text=True, timeout=120)
    if probe.returncode:
        last = (probe.stderr.strip().splitlines() or ["?"])[-1]
        why = last_error_line(log)
        pytest.skip(f"{python} cannot import btf_extractor and pysmtb ({last}); `make readers` rebuilds "
                    "the venv" + (f" (its log {log} ends: {why!r})" if why else ""))
    return python


def run_reader(python: Path, reader: str, path: Path) -> subprocess.CompletedProcess:
    out = path.with_name(f"{path.stem}.{reader}.npz")
    return subprocess.run([str(python), str(SCRIPT), reader, str(path), str(out)], capture_output=True,
                          text=True, timeout=300, cwd=path.parent)


def read_with(python: Path, reader: str, path: Path) -> dict[str, np.ndarray]:
    """What ``reader`` returns for ``path``, as saved by bonn_readers.py."""
    proc = run_reader(python, reader, path)
    hint = (" (a negative status is a signal: btf.hh's LoadBTF rejected the file, returned NULL and "
            "btf-extractor dereferenced it)") if proc.returncode < 0 else ""
    assert proc.returncode == 0, f"{reader} failed on {path} with status {proc.returncode}{hint}:\n" \
                                 f"{proc.stderr[-3000:]}"
    with np.load(path.with_name(f"{path.stem}.{reader}.npz")) as saved:
        return {name: saved[name] for name in saved.files}


# --- files written by the project ---------------------------------------------------------------

def header(signature: str, n_rot: int):
    from tasks.bonn.header import make_header

    rotations = None
    if signature.endswith("R"):
        q = np.linalg.qr(np.random.default_rng(5).standard_normal((max(n_rot, 1), 3, 3)))[0]
        rotations = q[:n_rot].astype(np.float32)
    return make_header(np.deg2rad(VIEW_DEG), np.deg2rad(LIGHT_DEG), W, H, signature=signature,
                       xml="<measurement material=\"synthetic\"/>", measurement_setup="btf-pipeline test",
                       image_sensor="none", light_source="none", ppmm=12.5,
                       rgb_scale_factor=(1.0, 0.5, 0.25), rotations=rotations)


def rgb_factors(rng: np.random.Generator, ks=(9, 8, 3)):
    """Random per-channel factors of colour model 0: (S, U, SxV) lists; K 9 and 8 cover btf.hh's
    8-wide half-float SIMD steps and its remainder, 3 the remainder alone."""
    U = [rng.standard_normal((N_LV, k)) * 0.4 for k in ks]
    SxV = [rng.standard_normal((N_TX, k)) * 0.4 for k in ks]
    return [np.linalg.norm(s, axis=0) for s in SxV], U, SxV


def log_yuv_factors(rng: np.random.Generator):
    """Model 11 channels of seeded linear RGB in [0.02, 1.3] (some above 1, which btf.hh clamps),
    encoded by ``encode_colour`` and factorised exactly (k = n_lv) per channel."""
    from btfcore.bonn import encode_colour, factorise

    rgb = rng.uniform(0.02, 1.3, size=(N_LV, N_TX, 3))
    channels, mean, matrix = encode_colour(rgb, 11)
    S, U, SxV = zip(*(factorise(np.asarray(channels[..., c], np.float64), N_LV) for c in range(3)))
    return list(S), list(U), list(SxV), mean, matrix


@dataclasses.dataclass
class Written:
    """What was handed to a writer: per-channel factors (FMF: views of its one U and SxV), the colour model."""

    S: list
    U: list
    SxV: list
    scalar_size: int
    model: int = 0
    mean: np.ndarray | None = None
    matrix: np.ndarray | None = None

    def cast(self, name: str, c: int) -> np.ndarray:
        """Factor ``name`` of channel ``c`` in the file's dtype: what a reader must find."""
        return np.asarray(getattr(self, name)[c]).astype({2: np.float16, 4: np.float32}[self.scalar_size])

    def channels(self, absolute: bool = False) -> np.ndarray:
        """``(n_lv, h, w, 3)`` float64 products ``U_c SxV_c^T`` of the factors as stored (texel x + w y);
        ``absolute``: ``|U_c| |SxV_c|^T``, the scale of each value's terms."""
        f = np.abs if absolute else np.asarray
        return np.stack([f(self.cast("U", c).astype(np.float64)) @ f(self.cast("SxV", c).astype(np.float64)).T
                         for c in range(3)], axis=-1).reshape(N_LV, H, W, 3)


def write_dfmf(path: Path, scalar_size: int, model: int, n_rot: int, seed: int = 0,
               **header_fields) -> tuple[Path, Written]:
    from tasks.bonn.dfmf import write_dfmf as write

    rng = np.random.default_rng(seed)
    if model == 11:
        S, U, SxV, mean, matrix = log_yuv_factors(rng)
    else:
        (S, U, SxV), mean, matrix = rgb_factors(rng), np.zeros(3, np.float32), np.eye(3, dtype=np.float32)
    hd = dataclasses.replace(header("!DFMF08FCR", n_rot), **header_fields)
    write(path, hd, model, mean, matrix, S, U, SxV, scalar_size=scalar_size)
    return path, Written(list(S), list(U), list(SxV), scalar_size, model, mean, matrix)


def decode_ours(path: Path) -> tuple[np.ndarray, np.ndarray, object]:
    """Our decode of ``path``: (channels as stored, the value a reader returns) ``(n_lv, h, w, 3)`` float32,
    and the Factorised object."""
    from btfcore.bonn import decode_colour, decode_textures, restore_dynamic_range
    from tasks.bonn.dfmf import read_factorised

    fact = read_factorised(path)
    channels = decode_textures(fact.U, fact.SxV, slice(None))
    values = decode_colour(channels, fact.colour_model, fact.colour_mean, fact.colour_matrix)
    if fact.dynamic_range_reduced:
        values = restore_dynamic_range(values)
    shape = (fact.header.n_lv, fact.header.height, fact.header.width, 3)
    return channels.reshape(shape), np.asarray(values).reshape(shape), fact


def assert_within(actual: np.ndarray, expected: np.ndarray, bound: np.ndarray, what: str) -> None:
    err = np.abs(np.asarray(actual, np.float64) - np.asarray(expected, np.float64))
    worst = np.unravel_index(np.argmax(err - bound), err.shape)
    assert np.all(err <= bound), (f"{what}: {int(np.sum(err > bound))} of {err.size} values differ by more "
                                  f"than the bound; worst at {worst}: {actual[worst]} vs {expected[worst]} "
                                  f"(bound {bound[worst]:.3g})")


# --- btf-extractor ------------------------------------------------------------------------------

def undo_btf_hh(saved: dict[str, np.ndarray]) -> np.ndarray:
    """btf-extractor's ``images`` ``(n_v, n_l, h, w, 3)`` BGR, rows flipped -> ``(n_lv, h, w, 3)`` RGB in
    our orientation, row ``l + n_l * v``."""
    images = saved["images"]
    return images[:, :, ::-1, :, ::-1].reshape((-1,) + images.shape[2:])


def btf_hh_model_11(channels: np.ndarray) -> np.ndarray:
    """btf.hh's decode of colour model 11: U = c1 Y + eps (btflib: c1 (Y + eps)), RGB clamped to [0, 1]."""
    eps = 1e-5
    y = np.exp(channels[..., 0].astype(np.float64)) - eps
    yuv = np.stack([y, channels[..., 1] * y + eps, channels[..., 2] * y + eps], axis=-1)
    return np.clip(yuv @ YUV_TO_RGB.T, 0.0, 1.0)


def check_btf_extractor_geometry(saved: dict[str, np.ndarray]) -> None:
    """Sizes and its angle table (degrees, rounded to 0.1 by the reader) against what was written."""
    assert (int(saved["n_l"]), int(saved["n_v"])) == (N_L, N_V)
    assert saved["images"].shape == (N_V, N_L, H, W, 3)
    assert tuple(saved["img_shape"]) == (W, H, 3)        # its quirk: (width, height, 3), images are (h, w, 3)
    keys, index = saved["angle_keys"], saved["angle_index"]
    assert len(keys) == N_LV and sorted(map(tuple, index)) == [(l, v) for l in range(N_L) for v in range(N_V)]
    expected = np.concatenate([LIGHT_DEG[index[:, 0]], VIEW_DEG[index[:, 1]]], axis=1)
    theta_err = np.abs(keys[:, [0, 2]] - expected[:, [0, 2]])
    phi_err = np.abs((keys[:, [1, 3]] - expected[:, [1, 3]] + 180.0) % 360.0 - 180.0)
    phi_err[expected[:, [0, 2]] == 0.0] = 0.0             # azimuth of the pole: undefined
    assert theta_err.max() <= 0.051 and phi_err.max() <= 0.051, (theta_err.max(), phi_err.max())


DFMF_CASES = {"half-rgb-rot2": (2, 0, 2), "single-rgb": (4, 0, 0), "half-logyuv": (2, 11, 0),
              "single-logyuv-rot1": (4, 11, 1)}


def model_11_bound(channels: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """How far model-11 RGB can move when each channel ``c_i`` moves by up to ``delta_i``
    (``Y = exp(c0)``, ``U = c1 Y``, ``V = c2 Y``, then ``YUV_TO_RGB``), plus half-float precision of the
    terms of the result."""
    c = channels.astype(np.float64)
    y = np.exp(c[..., 0])
    d_yuv = np.stack([y * delta[..., 0], y * (np.abs(c[..., 1]) * delta[..., 0] + delta[..., 1]),
                      y * (np.abs(c[..., 2]) * delta[..., 0] + delta[..., 2])], axis=-1)
    terms = np.stack([y, np.abs(c[..., 1]) * y, np.abs(c[..., 2]) * y], axis=-1)
    return (d_yuv + HALF * terms) @ np.abs(YUV_TO_RGB).T


@pytest.mark.parametrize("case", sorted(DFMF_CASES))
def test_btf_extractor_reads_our_dfmf(readers, tmp_path, case) -> None:
    from btfcore.bonn import DRR_EPS

    scalar_size, model, n_rot = DFMF_CASES[case]
    path, written = write_dfmf(tmp_path / f"{case}.btf", scalar_size, model, n_rot)
    saved = read_with(readers, "btf-extractor", path)
    check_btf_extractor_geometry(saved)
    theirs = undo_btf_hh(saved)
    intended, delta = written.channels(), HALF * written.channels(absolute=True)
    channels, ours, _ = decode_ours(path)
    if model == 0:
        assert_within(theirs, intended, delta, f"btf-extractor vs the factors written to {case}")
        assert_within(theirs, ours, delta, f"btf-extractor vs our decode of {case}")
        return
    # model 11: their formula on the written channels, then our btflib decode where they differ
    assert_within(theirs, btf_hh_model_11(intended), model_11_bound(intended, delta),
                  f"btf-extractor vs btf.hh's model 11 on the channels written to {case}")
    assert np.any(ours > 1.0) and theirs.max() <= 1.0, "the data should show btf.hh's clamp to [0, 1]"
    eps_placement = 3.0 * DRR_EPS * (1.0 + np.abs(channels[..., 1:]).sum(-1, keepdims=True))
    assert_within(theirs, np.clip(ours, 0.0, 1.0), model_11_bound(channels, delta) + eps_placement,
                  f"btf-extractor vs our decode_colour (clamped) of {case}")


def test_btf_extractor_ignores_other_colour_models_and_the_cosine_flag(readers, tmp_path) -> None:
    """btf.hh decodes models 0 and 11 only and stubs the cosine flag with an ``assert`` that its release
    build compiles out: a YUV (model 1) file with the flag set comes back as the raw channels."""
    path, written = write_dfmf(tmp_path / "yuv-cosine.btf", 4, 1, 0, seed=3, cosine_flag=True)
    channels, ours, fact = decode_ours(path)
    assert fact.header.cosine_flag and fact.colour_model == 1
    theirs = undo_btf_hh(read_with(readers, "btf-extractor", path))
    delta = HALF * written.channels(absolute=True)
    assert_within(theirs, written.channels(), delta, "btf-extractor vs the written channels (not RGB)")
    assert np.abs(ours - channels).max() > 0.1, "our YUV decode should differ from the raw channels"


def test_btf_extractor_crashes_when_views_and_lights_differ(readers, tmp_path) -> None:
    """btf.hh wants DFMF rows = n_l^2; on a file it refuses, LoadBTF returns NULL and btf-extractor
    dereferences it or frees a bad pointer. A valid file with n_v != n_l (ours reads it) kills the
    process: SIGSEGV here, SIGABRT from glibc's free() on CI's build, so any fatal signal counts."""
    from tasks.bonn.dfmf import read_factorised, write_dfmf as write
    from tasks.bonn.header import make_header

    n_v = 2
    hd = make_header(np.deg2rad(VIEW_DEG[:n_v]), np.deg2rad(LIGHT_DEG), W, H, signature="!DFMF08FCR")
    rng = np.random.default_rng(4)
    U = [rng.standard_normal((N_L * n_v, 3)) for _ in range(3)]
    SxV = [rng.standard_normal((N_TX, 3)) for _ in range(3)]
    path = tmp_path / "two-views.btf"
    write(path, hd, 0, np.zeros(3, np.float32), np.eye(3, dtype=np.float32), [np.ones(3)] * 3, U, SxV)
    assert (read_factorised(path).header.n_v, read_factorised(path).header.n_l) == (n_v, N_L)
    proc = run_reader(readers, "btf-extractor", path)
    fatal = {-signal.SIGSEGV, -signal.SIGABRT, -signal.SIGBUS}
    assert proc.returncode in fatal, (proc.returncode, proc.stderr[-2000:])

FMF_CASES = {"fmf12-half-drr-heightmap-rot1": ("!FMF12FCER", 2, True, True, 1),
             "fmf12-single": ("!FMF12FCER", 4, False, False, 0),
             "fmf06-half-no-rotations-block": ("!FMF06FC", 2, False, False, 0),
             "fmf06R-single": ("!FMF06FCR", 4, False, False, 2)}


def write_fmf(path: Path, case: str, seed: int = 1) -> tuple[Path, Written]:
    from tasks.bonn.dfmf import write_fmf as write

    signature, scalar_size, drr, height_map, n_rot = FMF_CASES[case]
    rng = np.random.default_rng(seed)
    k = 11
    U = rng.standard_normal((3 * N_LV, k)) * 0.4           # rows c + 3 (l + n_l v): channel fastest
    SxV = rng.standard_normal((N_TX, k)) * 0.4
    S = np.linalg.norm(SxV, axis=0)
    hmap = rng.uniform(0, 1, size=(H, W)).astype(np.float16) if height_map else None
    write(path, header(signature, n_rot), S, U, SxV, scalar_size=scalar_size, dynamic_range_reduced=drr,
          height_map=hmap, extended=signature.startswith("!FMF12"))
    return path, Written([S] * 3, [U[c::3] for c in range(3)], [SxV] * 3, scalar_size)


@pytest.mark.parametrize("case", sorted(FMF_CASES))
def test_btf_extractor_reads_our_fmf(readers, tmp_path, case) -> None:
    from btfcore.bonn import DRR_EPS

    path, written = write_fmf(tmp_path / f"{case}.btf", case)
    saved = read_with(readers, "btf-extractor", path)
    check_btf_extractor_geometry(saved)
    theirs = undo_btf_hh(saved)
    intended, delta = written.channels(), HALF * written.channels(absolute=True)
    _, ours, fact = decode_ours(path)
    assert fact.dynamic_range_reduced == FMF_CASES[case][2]
    if fact.dynamic_range_reduced:                        # exp(x) - eps: the error scales with exp(x)
        intended, delta = np.exp(intended) - DRR_EPS, np.exp(intended) * (delta + HALF)
    assert_within(theirs, intended, delta, f"btf-extractor vs the factors written to {case}")
    assert_within(theirs, ours, delta, f"btf-extractor vs our decode of {case}")


# --- pysmtb -------------------------------------------------------------------------------------

def padded(text: str) -> np.ndarray:
    return np.frombuffer(text.encode().ljust(80, b"\0"), np.uint8)


PYSMTB_CASES = {"half-rgb": (2, 0), "single-rgb": (4, 0), "half-logyuv": (2, 11), "single-logyuv": (4, 11)}


@pytest.mark.parametrize("case", sorted(PYSMTB_CASES))
def test_pysmtb_reads_our_dfmf(readers, tmp_path, case) -> None:
    from btfcore.bonn import decode_colour
    from tasks.bonn.header import sph_to_dir

    scalar_size, model = PYSMTB_CASES[case]
    path, written = write_dfmf(tmp_path / f"{case}.btf", scalar_size, model, n_rot=0)
    saved = read_with(readers, "pysmtb", path)
    hd = header("!DFMF08FCR", 0)
    meta = {k.removeprefix("meta."): v for k, v in saved.items() if k.startswith("meta.")}
    assert (int(meta["width"]), int(meta["height"]), int(meta["num_views"]), int(meta["num_lights"])) \
        == (W, H, N_V, N_L)
    assert int(meta["color_model"]) == model and int(meta["num_channels"]) == 3
    np.testing.assert_array_equal(meta["color_mean"], np.asarray(written.mean, np.float32))
    np.testing.assert_array_equal(meta["color_transformation_matrix"], np.asarray(written.matrix, np.float32))
    assert [bytes(meta[f"channel_names.{c}"]).decode() for c in range(3)] == ["R", "G", "B"]
    assert bytes(meta["xml"]).decode() == hd.xml and int(meta["cosine_in_data"]) == 0
    assert np.array_equal(meta["measurement_setup"], padded(hd.measurement_setup))
    assert np.float32(meta["ppmm"]) == np.float32(12.5)
    assert tuple(np.float32(meta["rgb_scale_factor"])) == (1.0, 0.5, 0.25)
    assert int(meta["num_rotations"]) == 0 and meta["rotations"].shape == (0, 3, 3)
    # angles: it keeps view directions in 3D, lights as stereographic 2D coordinates only
    views = sph_to_dir(np.deg2rad(VIEW_DEG).astype(np.float32))
    lights = sph_to_dir(np.deg2rad(LIGHT_DEG).astype(np.float32))
    np.testing.assert_allclose(meta["views_3d"], views, atol=1e-6)
    np.testing.assert_allclose(meta["lights_2d"], np.broadcast_to(lights[:, :2] / (1.0 + lights[:, 2:]),
                                                                  (N_V, N_L, 2)), atol=1e-6)
    # the factors, bit for bit as written
    for c in range(3):
        for name in ("S", "U", "SxV"):
            got, want = saved[f"data.{name}.{c}"], written.cast(name, c)
            assert got.dtype == want.dtype and np.array_equal(got, want), f"{name}[{c}] of {case}"
    # its texel convention (its crop reshapes SxV to (height, width, K)) decodes to the written channels
    channels = np.stack([np.einsum("lk,yxk->lyx", saved[f"data.U.{c}"].astype(np.float64),
                                   saved[f"data.SxV.{c}"].astype(np.float64).reshape(H, W, -1))
                         for c in range(3)], axis=-1)
    np.testing.assert_allclose(channels, written.channels(), rtol=1e-12, atol=1e-12)
    # and, through the colour model it reports, to our decode
    _, ours, fact = decode_ours(path)
    theirs = decode_colour(channels.astype(np.float32), int(meta["color_model"]), meta["color_mean"],
                           meta["color_transformation_matrix"])
    np.testing.assert_allclose(theirs, ours, rtol=1e-5, atol=1e-5)


def test_pysmtb_cannot_read_a_rotations_block(readers, tmp_path) -> None:
    """pysmtb reads 3 floats per rotation, not 9: any n_rot > 0 fails to reshape (its bug, documented)."""
    path, _ = write_dfmf(tmp_path / "rotations.btf", 2, 0, n_rot=2)
    proc = run_reader(readers, "pysmtb", path)
    assert proc.returncode == 1 and "reshape" in proc.stderr, proc.stderr[-2000:]
    assert read_with(readers, "btf-extractor", path)["images"].shape == (N_V, N_L, H, W, 3)


def test_last_error_line_of_a_failed_build_log(tmp_path) -> None:
    log = tmp_path / "venv.log"
    assert last_error_line(log) == ""
    log.write_text("Collecting btf-extractor\n  error: subprocess-exited-with-error\n"
                   "ERROR: Failed building wheel for btf-extractor\n\nFAILED to build venv after 9 s\n")
    assert last_error_line(log) == "ERROR: Failed building wheel for btf-extractor"
    log.write_text("Collecting x\nFAILED to build venv after 1 s\n")
    assert last_error_line(log) == "FAILED to build venv after 1 s"
