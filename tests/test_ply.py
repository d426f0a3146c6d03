"""kit.ply.read_gaussian_ply against PLY files written here byte by byte (graphdeco's layout)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polargs_plugin.io import PolarInputError
from polargs_plugin.kit.ply import read_gaussian_ply


def _write(path, columns: dict[str, np.ndarray], order: str = "<", fmt: str = "binary_little_endian",
           count: int | None = None, comments=("made by the test",)) -> None:
    """A PLY with one float vertex property per entry of ``columns``, in that order."""
    n = len(next(iter(columns.values())))
    header = ["ply", f"format {fmt} 1.0", *(f"comment {c}" for c in comments), f"element vertex {n if count is None else count}"]
    header += [f"property float {name}" for name in columns] + ["end_header"]
    rows = np.zeros(n, dtype=[(name, order + "f4") for name in columns])
    for name, values in columns.items():
        rows[name] = values
    path.write_bytes(("\n".join(header) + "\n").encode() + rows.tobytes())


def _graphdeco(n: int, degree: int, scales: int = 3, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    cols = {k: rng.normal(size=n) for k in ("x", "y", "z")}
    cols.update({k: np.zeros(n) for k in ("nx", "ny", "nz")})
    cols.update({f"f_dc_{i}": rng.normal(size=n) for i in range(3)})
    cols.update({f"f_rest_{i}": rng.normal(size=n) for i in range(3 * ((degree + 1) ** 2 - 1))})
    cols["opacity"] = rng.normal(size=n)
    cols.update({f"scale_{i}": rng.normal(size=n) - 3 for i in range(scales)})
    cols.update({f"rot_{i}": rng.normal(size=n) for i in range(4)})
    return cols


@pytest.mark.parametrize("order,fmt", [("<", "binary_little_endian"), (">", "binary_big_endian")])
def test_values_and_sh_layout(tmp_path, order, fmt):
    cols = _graphdeco(5, degree=2)
    _write(tmp_path / "g.ply", cols, order, fmt)
    g = read_gaussian_ply(tmp_path / "g.ply")
    assert g.sh_degree == 2 and g.comments == ["made by the test"]
    f32 = lambda a: torch.from_numpy(a.astype(np.float32))  # noqa: E731
    assert torch.equal(g["means"], torch.stack([f32(cols[k]) for k in "xyz"], 1))
    assert torch.equal(g["sh_dc"][:, 0, 1], f32(cols["f_dc_1"]))
    assert g["sh_rest"].shape == (5, 8, 3)
    # channel-major in the file: band row k of channel c is f_rest_{8 c + k}
    for c in range(3):
        for k in range(8):
            assert torch.equal(g["sh_rest"][:, k, c], f32(cols[f"f_rest_{8 * c + k}"]))
    assert torch.equal(g["opacity_logits"], f32(cols["opacity"]))
    assert torch.equal(g["log_scales"][:, 2], f32(cols["scale_2"]))
    assert torch.equal(g["quats"][:, 0], f32(cols["rot_0"]))  # w first, as stored


def test_degree_zero_and_a_2dgs_file(tmp_path):
    cols = _graphdeco(4, degree=0, scales=2)
    _write(tmp_path / "s.ply", cols)
    g = read_gaussian_ply(tmp_path / "s.ply")
    assert g.sh_degree == 0 and g["sh_rest"].shape == (4, 0, 3)
    smaller = np.minimum(cols["scale_0"], cols["scale_1"]).astype(np.float32)
    assert torch.allclose(g["log_scales"][:, 2], torch.from_numpy(smaller) - np.log(1e3))


def test_refusals_name_the_file(tmp_path):
    path = tmp_path / "bad.ply"
    cols = _graphdeco(3, degree=1)
    del cols["opacity"]
    _write(path, cols)
    with pytest.raises(PolarInputError, match=r"bad\.ply: not a Gaussian PLY: missing vertex properties opacity"):
        read_gaussian_ply(path)
    cols = _graphdeco(3, degree=1)
    _write(path, cols, count=4)
    with pytest.raises(PolarInputError, match="promises 4 vertices, the file holds 3"):
        read_gaussian_ply(path)
    _write(path, cols, fmt="ascii")
    with pytest.raises(PolarInputError, match="format 'ascii' is not supported"):
        read_gaussian_ply(path)
    del cols["f_rest_8"]  # 8 of 9 band coefficients: no SH degree
    _write(path, cols)
    with pytest.raises(PolarInputError, match="8 f_rest properties are no SH degree's"):
        read_gaussian_ply(path)
    cols = _graphdeco(3, degree=1)
    cols["x"][1] = np.nan
    _write(path, cols)
    with pytest.raises(PolarInputError, match="1 of 3 Gaussians have non-finite means"):
        read_gaussian_ply(path)
    path.write_bytes(b"solid mesh\n")
    with pytest.raises(PolarInputError, match="not a PLY file"):
        read_gaussian_ply(path)
    with pytest.raises(PolarInputError, match="no such Gaussian PLY file"):
        read_gaussian_ply(tmp_path / "absent.ply")
