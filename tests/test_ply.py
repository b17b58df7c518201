"""PLY writer and reader: round trips, the exact header, and refusals."""

import numpy as np
import pytest
import torch

from ngp_warp.outputs.ply import read_ply, write_ply


def test_mesh_round_trip_and_header(tmp_path):
    vertices = torch.randn(7, 3)
    colors = torch.randint(0, 256, (7, 3), dtype=torch.uint8)
    faces = torch.randint(0, 7, (5, 3))
    path = write_ply(tmp_path / "mesh.ply", vertices, colors, faces)
    data = read_ply(path)
    assert np.array_equal(data["vertices"], vertices.numpy())
    assert np.array_equal(data["colors"], colors.numpy())
    assert np.array_equal(data["faces"], faces.numpy().astype(np.int32))
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header\n")].decode().splitlines()
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 7"]
    assert "element face 5" in header and "property list uchar int vertex_indices" in header
    assert len(raw) == raw.index(b"end_header\n") + 11 + 7 * 15 + 5 * 13  # packed records
    assert [p.name for p in tmp_path.iterdir()] == ["mesh.ply"]  # nothing temporary left


def test_points_without_colours(tmp_path):
    points = np.random.default_rng(0).normal(size=(4, 3)).astype(np.float64)
    data = read_ply(write_ply(tmp_path / "points.ply", points))
    assert np.allclose(data["vertices"], points, atol=1e-6) and data["vertices"].dtype == np.float32
    assert data["colors"] is None and data["faces"] is None


def test_refusals(tmp_path):
    with pytest.raises(ValueError, match="vertices must have shape"):
        write_ply(tmp_path / "a.ply", torch.zeros(3, 2))
    with pytest.raises(ValueError, match="colors has 2 rows"):
        write_ply(tmp_path / "a.ply", torch.zeros(3, 3), torch.zeros(2, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="outside"):
        write_ply(tmp_path / "a.ply", torch.zeros(3, 3), faces=torch.tensor([[0, 1, 3]]))
    assert not any(tmp_path.iterdir())
    (tmp_path / "b.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(ValueError, match="binary little-endian"):
        read_ply(tmp_path / "b.ply")
    (tmp_path / "c.ply").write_bytes(b"solid x\n")
    with pytest.raises(ValueError, match="not a PLY"):
        read_ply(tmp_path / "c.ply")
