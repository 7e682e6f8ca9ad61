"""`report`: the model against the measurements.

The pieces on inputs with known answers (phases from contacts, the video's pixel noise, point tracks
of a known shift, whiteness of white and AR(1) series, correlation at a known lag), then the verb on
a tiny scene with a known answer (tests/report_scene.py, frames rendered at E_TRUE): the right fit
explains the video to the noise floor; E x10 authored over the fitted field and re-simulated is
inadequate from frames after the release on; a damping the model lacks fails only once the hand has
let go, with residuals that are not white. Plus the design's JSON keys, the residual primvars on
the stage, the outputs (HTML, MP4, PNG), the user's files untouched, bad input exit 2."""

import json
import shutil

import numpy as np
import pytest

import report_scene as rs
from physinteract_usd import api
from physinteract_usd.cli import main
from physinteract_usd.compare import frame_phases, pixel_noise
from physinteract_usd.compare.residuals import autocorrelation, cross_correlation, particle_map
from physinteract_usd.contacts import ContactSet
from physinteract_usd.errors import InputError
from physinteract_usd.usd.layout import LayerPaths

pytestmark = pytest.mark.usefixtures("one_torch_thread")
QUIET = dict(progress=False, log=lambda *a: None)


# ------------------------------------------------------------------------------ the pieces
def test_phases_from_grasp_release_and_the_hands_motion():
    traj = np.zeros((12, 3))
    traj[3:6, 1] = np.linspace(0.01, 0.03, 3)   # moves into frames 3, 4, 5
    traj[6:] = traj[5]
    hand = ContactSet("hand", "pointAdherent", [0], grasp_frame=2, release_frame=8, trajectory=traj)
    support = ContactSet("support", "fixed", [1])
    ph = frame_phases([hand, support], 12, fps=20.0)   # release lasts 0.15 s = 3 frames
    assert ph == ["rest", "rest", "hold", "load", "load", "load", "hold", "hold",
                  "release", "release", "release", "free"]
    # a fitted trajectory overrides the contact's own; never released: no release / free
    still = {"hand": np.zeros((12, 3))}
    assert frame_phases([hand.replace(release_frame=None)], 12, 20.0, still) == ["rest", "rest"] + ["hold"] * 10
    assert frame_phases([support], 4, 20.0) == ["rest", "free", "free", "free"]


def test_pixel_noise_is_measured_on_the_static_background():
    rng = np.random.default_rng(0)
    base = rng.uniform(0.2, 0.8, (1, 40, 50, 3)).astype(np.float32)
    frames = np.repeat(base, 6, 0) + rng.normal(0, 0.02, (6, 40, 50, 3)).astype(np.float32)
    cover = np.zeros((6, 40, 50), bool)
    cover[:, 10:25, 10:30] = True
    frames[:, 10:25, 10:30] = rng.uniform(0, 1, (6, 15, 20, 3))   # a moving object: not noise
    assert pixel_noise(frames, cover) == pytest.approx(0.02, rel=0.15)
    clean = np.repeat(np.round(base * 255) / 255, 6, 0)
    assert pixel_noise(clean, None) == pytest.approx(1 / 255 / np.sqrt(12))


def test_measured_tracks_follow_a_known_shift_and_stop_at_the_hand():
    import cv2

    from physinteract_usd.extract.track import measure_tracks

    rng = np.random.default_rng(1)
    tex = cv2.GaussianBlur(rng.uniform(0, 1, (48, 64, 3)).astype(np.float32), (0, 0), 1.2)
    shifts = [(0, 0), (0.4, 0.2), (1.0, -0.5), (1.6, 0.7)]
    frames = np.stack([cv2.warpAffine(tex, np.float32([[1, 0, dx], [0, 1, dy]]), (64, 48),
                                      borderMode=cv2.BORDER_REFLECT) for dx, dy in shifts])
    pts = np.stack(np.meshgrid(np.arange(16, 48, 4) + 0.5, np.arange(12, 36, 4) + 0.5), -1).reshape(-1, 2)
    t = measure_tracks(frames, pts)
    for k, (dx, dy) in enumerate(shifts):
        ok = t.valid[k]
        assert ok.mean() > 0.9, k
        err = np.linalg.norm(t.uv[k][ok] - (pts[ok] + [dx, dy]), axis=1)
        assert np.median(err) < 0.15, (k, np.median(err))
    stop = np.zeros(frames.shape[:3], bool)
    stop[2:, :, :32] = True                                   # a hand covers the left half from frame 2
    t = measure_tracks(frames, pts, stop=stop)
    left = pts[:, 0] < 30
    assert not t.valid[2:, left].any() and t.valid[2:, ~left].mean() > 0.9
    assert np.isnan(t.uv[3, left]).all()


def test_whiteness_and_input_correlation():
    rng = np.random.default_rng(2)
    T, n = 200, 30
    white = rng.normal(size=(T, n, 2))
    ar = np.zeros((T, n, 2))
    for t in range(1, T):
        ar[t] = 0.9 * ar[t - 1] + rng.normal(size=(n, 2))
    valid = np.ones((T, n), bool)
    assert autocorrelation(white, valid, 10)["white"]
    a = autocorrelation(ar, valid, 10)
    assert not a["white"] and a["r"][1] > 0.8
    u = rng.normal(size=T)
    e = np.roll(u, 3) + 0.3 * rng.normal(size=T)              # the residual follows the input by 3 frames
    x = cross_correlation(e, u, 6)
    assert x["lags"][int(np.argmax(x["r"]))] == 3 and not x["uncorrelated"]
    assert cross_correlation(rng.normal(size=T), u, 6)["uncorrelated"]


def test_particle_map_takes_the_nearest_measured_gaussians():
    g = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    v = np.array([1.0, np.nan, 3.0])                          # the middle one was never tracked
    p = particle_map(v, g, np.array([[0.0, 0.1, 0], [2.0, 0.1, 0], [1.0, 0, 0]]), k=1)
    np.testing.assert_allclose(p[:2], [1.0, 3.0])
    assert p[2] in (1.0, 3.0)
    assert np.isnan(particle_map(np.full(3, np.nan), g, g)).all()


def test_the_headline_says_from_when_and_how():
    from physinteract_usd.compare.verdict import headline, how_it_fails

    nan = float("nan")
    T = 8
    phases = ["rest", "load", "load", "hold", "release", "free", "free", "free"]
    floor = np.full(T, 0.25)
    fail = np.array([False] * 5 + [True] * 3)
    # the video comes to rest after the release, the model swings on
    code, words = how_it_fails(fail, [nan, 1, 1, 1, 1, 2.0, 1.5, 2.0], [nan, 1, 1, 1, 1, 0.1, 0.05, 0.02], floor, {})
    assert (code, words) == ("model_keeps_moving", "the model keeps moving, the video settles")
    err = [0, 0.1, 0.1, 0.1, 0.2, 2.0, 3.0, 2.5]
    h = headline(fail, phases, words, track_error=err, debiased=err, track_floor=floor, psnr_masked=[40.0] * T)
    assert h["verdict"] == "inadequate" and h["first_failing_frame"] == 5 and h["failing_phases"] == ["free"]
    assert h["headline"].startswith("inadequate from frame 5 on (free): the model keeps moving, the video settles;")
    assert h["headline"].endswith("worst at frame 6")
    # the reverse, and a sag read from the residual along gravity (positive: the video hangs lower)
    assert how_it_fails(fail, [nan, 1, 1, 1, 1, 0.1, 0.1, 0.1], [nan, 1, 1, 1, 1, 2, 2, 2], floor, {})[0] == \
        "video_keeps_moving"
    g = np.array([0, 0, 0, 0, 0, -0.004, -0.005, -0.004])
    code, words = how_it_fails(fail, [nan] * T, [nan] * T, floor, {"gravity": g, "velocity": g / 4})
    assert code == "gravity_over" and words.startswith("the model sags too much") and "4.3 mm" in words
    scattered = np.array([False, False, True, False, False, True, True, False])
    h = headline(scattered, phases, "x", track_error=err, debiased=err, track_floor=floor, psnr_masked=[40.0] * T)
    assert h["headline"].startswith("inadequate at frames 2, 5-6 (load, free): x")
    ok = headline(np.zeros(T, bool), phases, "", track_error=err, debiased=err, track_floor=floor, psnr_masked=[40.0] * T)
    assert ok["verdict"] == "adequate" and ok["failing_frames"] == []


# ------------------------------------------------------------------------------ the verb
@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return rs.build(tmp_path_factory.mktemp("report") / "base")


def _copy(scene, dst):
    shutil.copytree(scene["root"], dst)
    return dst / "scene.usda"


@pytest.fixture(scope="module")
def reported(scene, tmp_path_factory):
    """The right fit, reported with every output."""
    stage = _copy(scene, tmp_path_factory.mktemp("report") / "right")
    lp = LayerPaths.of(stage)
    root_before, init_before = lp.root.read_bytes(), lp.init.read_bytes()
    out = stage.parent / "out"
    out.mkdir()
    d = api.report(stage, html=out / "r.html", video=out / "r.mp4", frames_dir=out / "frames", **QUIET)
    return {"stage": stage, "data": d, "out": out, "root_before": root_before, "init_before": init_before}


def test_the_right_fit_explains_the_video_to_the_noise_floor(reported):
    d = reported["data"]
    assert d["verdict"] == "adequate", d["headline"]
    assert d["headline"].startswith("explains the data to the noise floor")
    assert d["failing_frames"] == [] and not any(f["fails"] for f in d["frames"])
    assert d["psnr_masked"] > 45 and d["iou"] > 0.97
    assert d["track_error_debiased_px"] < 0.2 and d["tracked_points"] > 100
    assert [f["phase"] for f in d["frames"]] == ["hold"] + ["load"] * 4 + ["release"] * 4 + ["free"]


def test_report_json_has_the_designs_keys(reported):
    d = reported["data"]
    for key in ("psnr", "psnr_masked", "ssim", "iou", "track_error_px"):
        assert isinstance(d[key], float), key
    assert len(d["frames"]) == rs.N_FRAMES
    for f in d["frames"]:
        assert {"frame", "psnr", "ssim", "iou", "phase"} <= set(f)
    assert [f["frame"] for f in d["frames"]] == list(range(rs.N_FRAMES))
    (v,) = d["versions"]
    assert v["version"] == 1 and v["effects"] == [] and v["loss"] == pytest.approx(0.001) and v["psnr"] > 90
    # the top-level numbers are the means over frames
    assert d["ssim"] == pytest.approx(np.mean([f["ssim"] for f in d["frames"]]))
    json.dumps(d, allow_nan=False)


def test_residual_maps_are_primvars_on_the_particles(reported):
    from pxr import Usd, UsdGeom

    from physinteract_usd.usd.report_io import read_residuals
    from physinteract_usd.usd.stage import read_stage

    stage = reported["stage"]
    maps = read_residuals(stage)
    assert set(maps) == {"all", "load", "release", "free"}        # frame 0 (hold) is zero by construction
    P = len(read_stage(stage).particles_positions)
    floor_m = 0.25 * reported["data"]["mm_per_px"] / 1000         # the tracker's noise floor, in metres
    for phase, v in maps.items():
        assert v.shape == (P,) and np.isfinite(v).all() and (v >= 0).all(), phase
        assert np.percentile(v, 90) < 2 * floor_m, phase          # the right fit: at the noise floor
    composed = Usd.Stage.Open(str(stage))
    pv = UsdGeom.PrimvarsAPI(composed.GetPrimAtPath("/World/Object/SimParticles"))
    p = pv.GetPrimvar("physinteract:residual_release")
    assert p.GetInterpolation() == UsdGeom.Tokens.vertex
    # written into the fit layer; the user's root and the init layer untouched
    lp = LayerPaths.of(stage)
    assert lp.root.read_bytes() == reported["root_before"] and lp.init.read_bytes() == reported["init_before"]
    from pxr import Sdf

    from pxr import UsdValidation

    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    assert not [e for e in ctx.Validate(composed) if e.GetType() == UsdValidation.ValidationErrorType.Error]
    fit = Sdf.Layer.FindOrOpen(str(lp.fit))
    assert fit.GetAttributeAtPath("/World/Object/SimParticles.primvars:physinteract:residual") is not None
    assert dict(fit.customLayerData)["physinteract"]["report"]["verdict"] == "adequate"


def test_outputs_html_mp4_and_frames(reported):
    import cv2

    out = reported["out"]
    html = (out / "r.html").read_text()
    assert html.count("data:image/png;base64,") == 5 + rs.N_FRAMES     # 5 plots, every frame
    assert "src=\"http" not in html and "<link" not in html              # self-contained
    assert "explains the data to the noise floor" in html
    cap = cv2.VideoCapture(str(out / "r.mp4"))
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    ok, first = cap.read()
    cap.release()
    assert ok and n == rs.N_FRAMES
    pngs = sorted((out / "frames").glob("*.png"))
    assert len(pngs) == rs.N_FRAMES
    im = cv2.imread(str(pngs[3]))
    assert im.shape[1] == 3 * rs.WIDTH * int(np.ceil(240 / rs.HEIGHT)) and first.shape[:2] == im.shape[:2]


def test_outputs_are_replaced_only_when_the_report_wrote_them(reported, tmp_path):
    stage, out = reported["stage"], reported["out"]
    again = api.report(stage, html=out / "r.html", video=out / "r.mp4", frames_dir=out / "frames", write_stage=False,
                       **QUIET)
    assert again["verdict"] == "adequate"                      # its own outputs: replaced
    mine = tmp_path / "notes.html"
    mine.write_text("my notes")
    with pytest.raises(InputError, match="not written by `report`"):
        api.report(stage, html=mine, write_stage=False, **QUIET)
    assert mine.read_text() == "my notes"
    (out / "frames" / "mine.txt").write_text("x")
    with pytest.raises(InputError, match="did not write"):
        api.report(stage, frames_dir=out / "frames", write_stage=False, **QUIET)


def test_a_wrong_stiffness_is_inadequate_where_it_fails(scene, tmp_path):
    """E x10 authored over the fitted field in the user's layer, re-simulated: inadequate, from the
    frames after the release on (where the stiff bar springs back and the video's does not); the same
    path with the fitted E is adequate."""
    stage = _copy(scene, tmp_path / "wrong")
    rs.author_youngs(stage, 1.0)
    same = api.report(stage, resimulate=True, write_stage=False, **QUIET)
    assert same["verdict"] == "adequate", same["headline"]
    rs.author_youngs(stage, 10.0)
    d = api.report(stage, resimulate=True, **QUIET)
    assert d["verdict"] == "inadequate" and d["resimulated"]
    first = d["first_failing_frame"]
    assert first is not None and rs.RELEASE <= first <= rs.RELEASE + 2, d["headline"]
    assert d["failing_frames"] == list(range(first, rs.N_FRAMES))
    assert d["headline"].startswith(f"inadequate from frame {first} on")
    assert d["track_error_debiased_px"] > 3 * same["track_error_debiased_px"]
    assert d["psnr_masked"] < same["psnr_masked"] - 15
    # where on the object: the free end (far from the support) moves most wrongly
    from physinteract_usd.usd.report_io import read_residuals
    from physinteract_usd.usd.stage import read_stage

    x0 = read_stage(stage).particles_positions
    res = read_residuals(stage)["free"]
    tip, root = x0[:, 0] > np.percentile(x0[:, 0], 80), x0[:, 0] < np.percentile(x0[:, 0], 20)
    assert res[tip].mean() > 3 * res[root].mean()


def test_a_missing_damping_fails_after_the_release_with_residuals_that_are_not_white(tmp_path):
    b = rs.build(tmp_path / "damped", hidden_damping=40.0, n_frames=18)
    d = api.report(b["stage"], write_stage=False, **QUIET)
    assert d["verdict"] == "inadequate"
    assert d["first_failing_frame"] >= rs.RELEASE
    assert set(d["failing_phases"]) <= {"release", "free"}
    assert not d["whiteness"]["white"] and d["whiteness"]["r"][1] > d["whiteness"]["band"]


# ------------------------------------------------------------------------------ the CLI
def test_cli_json_and_bad_input(reported, tmp_path, capsys):
    assert main(["report", str(reported["stage"]), "--json", "--no-stage"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["verdict"] == "adequate" and len(d["frames"]) == rs.N_FRAMES
    assert main(["report", str(tmp_path / "missing.usda")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "missing.usda" in err
    # a stage that was never fitted: one line naming it
    shutil.copytree(reported["stage"].parent / "capture", tmp_path / "capture")
    fresh = tmp_path / "fresh.usda"
    api.init(fresh, tmp_path / "capture", grid=8, padding=0.3)
    assert main(["report", str(fresh)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "fresh.usda" in err and "fit" in err


# ------------------------------------------------------------------------------ in a real browser
PROBE = """<script>window.addEventListener('load', function () {
  var out = [];
  document.querySelectorAll('img').forEach(function (im) {
    var r = im.getBoundingClientRect();
    out.push([r.left + window.scrollX, r.top + window.scrollY, r.width, r.height, im.naturalWidth, im.alt]);
  });
  var d = document.createElement('pre'); d.id = 'probe';
  d.textContent = JSON.stringify({imgs: out, height: document.documentElement.scrollHeight});
  document.body.appendChild(d);
});</script>"""
WHITE_PNG = ("iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8/5+hHgAHggJ/PchI7wAAAABJRU5ErkJggg==")


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def _browser(exe, tmp_path, *args):
    import subprocess

    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--force-device-scale-factor=1", "--hide-scrollbars", f"--user-data-dir={tmp_path / 'chromium-profile'}"]
    return subprocess.run([exe, *flags, *args], capture_output=True, text=True, timeout=120)


def test_the_html_page_renders_in_a_real_browser(reported, tmp_path):
    """Headless Chromium (Debian's `chromium`; scripts/test.sh installs it) renders the page: every
    plot and frame is decoded at its size, and in a screenshot each one's box holds a picture (many
    colours, far from the page's white), where the same page with the pictures blanked holds none."""
    import re

    import cv2

    exe = _chromium()
    if exe is None:
        pytest.skip("no chromium: scripts/test.sh installs Debian's chromium package")
    text = (reported["out"] / "r.html").read_text()
    probe = tmp_path / "probe.html"
    probe.write_text(text.replace("</body>", PROBE + "</body>"))
    r = _browser(exe, tmp_path, "--virtual-time-budget=5000", "--window-size=1280,1000", "--dump-dom", probe.as_uri())
    m = re.search(r'<pre id="probe">(.*?)</pre>', r.stdout, re.S)
    assert m, r.stderr[-2000:]
    info = json.loads(m.group(1).replace("&quot;", '"'))
    imgs = info["imgs"]
    assert len(imgs) == 5 + rs.N_FRAMES
    for x, y, w, h, natural, alt in imgs:
        assert natural > 100 and w > 300 and h > 100, (alt, w, h, natural)   # decoded, laid out at size

    # the page, and the same page with every picture replaced by white at the same size
    height = int(info["height"]) + 20
    counter = iter(imgs)
    blank = tmp_path / "blank.html"
    blank.write_text(re.sub(r'src="data:image/png;base64,[^"]*"',
                            lambda _: 'src="data:image/png;base64,{}" style="width:{}px;height:{}px"'.format(
                                WHITE_PNG, *(lambda i: (i[2], i[3]))(next(counter))), text))
    shots = {}
    for name, page in (("report", reported["out"] / "r.html"), ("blank", blank)):
        png = tmp_path / f"{name}.png"
        r = _browser(exe, tmp_path, f"--screenshot={png}", f"--window-size=1280,{height}", page.as_uri())
        assert png.exists(), r.stderr[-2000:]
        shots[name] = cv2.imread(str(png)).astype(np.float32)
    assert shots["report"].shape == shots["blank"].shape
    for x, y, w, h, _, alt in imgs:
        box = tuple(slice(int(a) + 2, int(a + b) - 2) for a, b in ((y, h), (x, w)))
        for name, want in (("report", True), ("blank", False)):
            region = shots[name][box]
            painted = (np.abs(region - 255).max(-1) > 30).mean()   # share of pixels far from white
            colours = len(np.unique((region // 32).reshape(-1, 3), axis=0))
            assert (painted > 0.02 and colours >= 4) == want, (name, alt, painted, colours)
