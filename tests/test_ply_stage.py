"""PLY decoding, stage attributes equal the decoded PLY values, PLY -> stage -> PLY round trip."""

import numpy as np
import pytest

from capture_factory import make_capture, sphere_gaussians
from physinteract_usd import api
from physinteract_usd.gaussians import Gaussians, read_ply, sigmoid, write_ply
from physinteract_usd.usd.layout import LayerPaths
from physinteract_usd.usd.stage import read_splats, read_stage
from pxr import Usd, UsdValidation, UsdVol


def _raw_ply(path):
    """Read the encoded PLY columns with plain numpy (independent of read_ply)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    n = int([h for h in header if h.startswith("element vertex")][0].split()[-1])
    names = [h.split()[-1] for h in header if h.startswith("property")]
    return np.frombuffer(data[end:], dtype=[(k, "<f4") for k in names], count=n)


def test_read_ply_decodes_the_inria_layout(tmp_path):
    g = sphere_gaussians(n=50, sh_degree=2)
    write_ply(g, tmp_path / "g.ply")
    raw = _raw_ply(tmp_path / "g.ply")
    back = read_ply(tmp_path / "g.ply")
    assert np.allclose(back.opacities, sigmoid(raw["opacity"].astype(np.float64)), rtol=1e-6)
    assert np.allclose(back.scales[:, 1], np.exp(raw["scale_1"].astype(np.float64)), rtol=1e-6)
    # f_rest is channel-major: 8 coefficients of R, then G, then B
    assert np.allclose(back.sh[:, 1 + 3, 1], raw["f_rest_11"], rtol=1e-6)  # G channel, coefficient 4
    assert np.allclose(back.sh[:, 0, 2], raw["f_dc_2"])
    assert np.allclose(np.linalg.norm(back.quats, axis=1), 1.0)
    colour = 0.5 + 0.28209479 * raw["f_dc_0"]
    assert np.allclose(back.colors[:, 0], np.clip(colour, 0, 1), atol=1e-6)


def test_unnormalised_quaternions_and_saturated_logits(tmp_path):
    g = sphere_gaussians(n=20)
    g.quats = g.quats * 3.0
    g.opacities[:3] = [1.0, 0.0, 0.5]  # saturating values get clamped logits
    write_ply(g, tmp_path / "g.ply")
    back = read_ply(tmp_path / "g.ply")
    assert np.allclose(np.linalg.norm(back.quats, axis=1), 1.0)
    assert back.opacities[0] == pytest.approx(1.0, abs=2e-6)
    assert back.opacities[1] == pytest.approx(0.0, abs=2e-6)


def test_stage_attributes_equal_decoded_ply_and_round_trip(tmp_path):
    cap = make_capture(tmp_path / "cap")
    ply = read_ply(cap / "object.ply")
    lp = api.init(tmp_path / "scene.usda", cap, grid=16)
    stage = Usd.Stage.Open(str(lp.root))
    prim = stage.GetPrimAtPath("/World/Object/Splats")
    assert prim.IsA(UsdVol.ParticleField3DGaussianSplat)
    sh_attr = UsdVol.ParticleFieldSphericalHarmonicsAttributeAPI(prim)
    assert sh_attr.GetRadianceSphericalHarmonicsDegreeAttr().Get() == ply.sh_degree
    usd_opac = np.array(UsdVol.ParticleFieldOpacityAttributeAPI(prim).GetOpacitiesAttr().Get())
    assert np.allclose(usd_opac, ply.opacities, rtol=1e-6)  # activated, not logits
    usd_scales = np.array(UsdVol.ParticleFieldScaleAttributeAPI(prim).GetScalesAttr().Get())
    assert np.allclose(usd_scales, ply.scales, rtol=1e-6)  # linear, not log
    g = read_splats(stage)
    assert np.allclose(g.sh, ply.sh, rtol=1e-6, atol=1e-7)
    assert np.allclose(np.abs(np.sum(g.quats * ply.quats, axis=1)), 1.0, atol=1e-6)
    # stage -> PLY -> decode equals the original PLY within 1e-6 relative
    write_ply(g, tmp_path / "back.ply")
    a, b = _raw_ply(cap / "object.ply"), _raw_ply(tmp_path / "back.ply")
    for k in a.dtype.names:
        if k in ("nx", "ny", "nz"):
            continue
        x, y = a[k].astype(np.float64), b[k].astype(np.float64)
        if k.startswith("rot_"):
            continue  # compared as rotations above (PLY quaternions are unnormalised)
        assert np.allclose(y, x, rtol=1e-6, atol=1e-6 * max(1.0, np.abs(x).max())), k


def test_composed_stage_validates_and_has_the_layout(tmp_path):
    cap = make_capture(tmp_path / "cap")
    lp = api.init(tmp_path / "scene.usda", cap, grid=16)
    assert lp == LayerPaths.of(tmp_path / "scene.usda")
    stage = Usd.Stage.Open(str(lp.root))
    root = stage.GetRootLayer()
    assert [p.split("/")[-1] for p in root.subLayerPaths] == ["scene.fit.usdc", "scene.init.usdc"]
    assert stage.GetDefaultPrim().GetPath() == "/World"
    from pxr import UsdGeom

    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdGeom.GetStageUpAxis(stage) == "Y"
    assert stage.GetTimeCodesPerSecond() == 24.0
    for path, t in [("/World/Object/Splats", "ParticleField3DGaussianSplat"),
                    ("/World/Object/SimParticles", "Points"), ("/World/Camera", "Camera"),
                    ("/World/PhysInteract", "PhysInteractScene")]:
        assert stage.GetPrimAtPath(path).GetTypeName() == t
    pts = stage.GetPrimAtPath("/World/Object/SimParticles")
    assert pts.HasAPI("PhysInteractMaterialFieldAPI")
    assert pts.GetAttribute("primvars:physinteract:youngsModulus").HasValue()
    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    errors = [e for e in ctx.Validate(stage) if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert errors == [], [e.GetMessage() for e in errors]
    sd = read_stage(lp.root)
    assert sd.n_frames == 4 and sd.fps == 24.0
    from scipy.spatial import cKDTree

    # every Gaussian has a particle next to it (the simulation binds each to its nearest ones)
    assert cKDTree(sd.particles_positions).query(sd.gaussians.means)[0].max() < 2 * sd.settings.particle_spacing


def test_mesh_object_keeps_its_mesh(tmp_path):
    cap = make_capture(tmp_path / "cap", object_kind="obj")
    lp = api.init(tmp_path / "scene.usda", cap, grid=16)
    stage = Usd.Stage.Open(str(lp.root))
    assert stage.GetPrimAtPath("/World/Object/Mesh").GetTypeName() == "Mesh"
    g = read_splats(stage)
    assert len(g) > 1000
    assert np.allclose(g.colors.mean(0), np.array([200, 80, 40]) / 255, atol=0.02)
    sd = read_stage(lp.root)
    assert sd.object_kind == "mesh"
    # the fill's total volume equals the mesh volume
    import trimesh

    assert sd.particles_volumes.sum() == pytest.approx(trimesh.creation.icosphere(2, radius=0.1).volume, rel=1e-4)


def test_gaussians_from_colors_roundtrip():
    g = Gaussians.from_colors(np.zeros((3, 3)), [0.2, 0.4, 0.9], 0.01)
    assert np.allclose(g.colors, [0.2, 0.4, 0.9])
    assert g.scales.shape == (3, 3)
