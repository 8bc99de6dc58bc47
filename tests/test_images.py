"""AFM images: the real Nanosurf grating, TIFF, Gwyddion and TopoStats files, the jaxafm
image format, scans as images, bad input, and the image metadata a config gives (``ImageFile``)
through every mode that reads images."""

import json
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tifffile
import yaml

import jaxafm
from jaxafm.config import CalibrateConfig, ConfigError, DiagnoseConfig, ImageFile, load_config
from jaxafm.instrument.afm import Raster, default_afm, raster_scan
from jaxafm.instrument.images import (
    AFMImage,
    from_scan,
    load_image,
    read_image,
    save_image,
)
from jaxafm.instrument.samples import Grating
from jaxafm.jobs import Output
from jaxafm.jobs.inputs import read_image_file, read_image_pair, scan_settings

GRATING_FILE = Path(jaxafm.__file__).parent / "data" / "real" / "grating_1d_nanosurf.txt"


def test_real_nanosurf_grating_reads_in_nm_with_the_readme_facts():
    im = read_image(GRATING_FILE)
    assert im.shape == (128, 128)
    assert np.allclose(im.pixel_size, (78.125, 78.125)) and np.allclose(im.size, (10_000.0, 10_000.0))
    assert im.meta["direction"] == "retrace" and "μm" in im.meta["converted"]
    assert 540 < np.ptp(im.z) < 600  # grooves about 550 nm deep
    # the period along x: about 2.89 µm (data README), from the spectrum of the mean row
    row = im.z.mean(axis=0) - im.z.mean()
    spectrum = np.abs(np.fft.rfft(row, n=8192))
    freq = np.fft.rfftfreq(8192, d=im.pixel_size[0])
    period = 1 / freq[1:][np.argmax(spectrum[1:])]
    assert 2800 < period < 2980


NID_FILE = GRATING_FILE.parent / "lattice_square_pits_nanosurf.nid"


def write_nid(
    path,
    frames: dict,
    size_m=(4e-6, 3e-6),
    z=(-2e-6, 4e-6),
    bits=16,
    direction="Up",
    scan=("Time/Line=0.5 s",),
):
    """A Nanosurf .nid file written from the format's description (the vendor's NSFopen reader):
    ``frames`` {frame: {channel: raw integers (lines, points)}}, heights
    ``z0 + (raw + 2^(bits-1)) / 2^bits * range`` m; ``scan``: the header's other scan entries."""
    head, data, sections = ["[DataSet]", "Version=2", f"GroupCount={len(frames)}"], [], []
    for g, (frame, channels) in enumerate(frames.items()):
        head += [f"Gr{g}-Name={frame}", f"Gr{g}-ID=0", f"Gr{g}-Count={len(channels) + 1}"]
        for c, (name, raw) in enumerate(channels.items(), start=1):
            head.append(f"Gr{g}-Ch{c}=DataSet-{g}:{c}")
            lines, points = raw.shape
            sections += [
                "",
                f"[DataSet-{g}:{c}]",
                f"Points={points}",
                f"Lines={lines}",
                f"Frame={frame}",
                f"Dim0Range={size_m[0]}",
                "Dim0Unit=m",
                f"Dim1Range={size_m[1]}",
                "Dim1Unit=m",
                f"Dim2Name={name}",
                f"Dim2Min={z[0]}",
                f"Dim2Range={z[1]}",
                "Dim2Unit=m",
                f"SaveBits={bits}",
            ]
            data.append(np.asarray(raw, f"<i{bits // 8}").tobytes())
    info = ["", "[DataSet\\DataSetInfos\\Scan]", f"Scan direction={direction}", *scan]
    text = "\r\n".join(head + info + sections) + "\r\n#!"
    path.write_bytes(text.encode() + b"".join(data))
    return path


def test_nid_file_reads_each_frame_and_channel_in_nm(tmp_path):
    rng = np.random.default_rng(1)
    raw = {k: rng.integers(-(2**15), 2**15, (6, 8)) for k in ("tf", "af", "tb")}
    path = write_nid(
        tmp_path / "a.nid",
        {
            "Scan forward": {"Topography": raw["tf"], "Amplitude": raw["af"]},
            "Scan backward": {"Topography": raw["tb"]},
        },
    )
    heights = lambda r: (-2e-6 + (r + 2.0**15) / 2.0**16 * 4e-6) * 1e9  # nm
    trace, retrace = read_image(path), read_image(path, direction="retrace")
    np.testing.assert_allclose(trace.z, heights(raw["tf"]), rtol=1e-12)
    np.testing.assert_allclose(retrace.z, heights(raw["tb"]), rtol=1e-12)
    assert trace.meta["direction"] == "trace" and retrace.meta["direction"] == "retrace"
    assert (
        np.allclose(trace.pixel_size, (500.0, 500.0)) and trace.meta["channel"] == "Topography (Scan forward)"
    )
    amplitude = read_image(path, channel="Amplitude")  # in m here; a real one is in V: refused below
    np.testing.assert_allclose(amplitude.z, heights(raw["af"]), rtol=1e-12)
    with pytest.raises(ValueError, match=r"no channel 'Amplitude' in the frame 'Scan backward'.*Topography"):
        read_image(path, channel="Amplitude", direction="retrace")
    down = write_nid(tmp_path / "d.nid", {"Scan forward": {"Topography": raw["tf"]}}, direction="Down")
    assert "row_order" not in read_image(down).meta  # the file does not say: stored order kept
    older = write_nid(tmp_path / "z.nid", {"Scan forward": {"Z-Axis": raw["tf"], "Amplitude": raw["af"]}})
    assert read_image(older).meta["channel"] == "Z-Axis (Scan forward)"  # older software's height
    np.testing.assert_allclose(read_image(older).z, heights(raw["tf"]), rtol=1e-12)
    (tmp_path / "b.nid").write_bytes(b"not a nanosurf file")
    with pytest.raises(ValueError, match=r"b\.nid is not a Nanosurf \.nid file"):
        read_image(tmp_path / "b.nid")


def test_real_nid_lattice_reads_its_header_and_both_directions():
    trace, retrace = read_image(NID_FILE), read_image(NID_FILE, direction="retrace")
    assert trace.shape == (256, 256) and np.allclose(trace.size, (50_000.0, 50_000.0))  # header: 5e-05 m
    assert (
        trace.meta["instrument"]["Time/Line"] == "2 s" and trace.meta["instrument"]["Scan direction"] == "Up"
    )
    assert 400 < np.percentile(trace.z, 98) - np.percentile(trace.z, 2) < 700  # pits about 490 nm deep
    with pytest.raises(ValueError, match="not lengths"):  # the amplitude is in V
        read_image(NID_FILE, channel="Amplitude")
    # one surface seen twice, in the same column order: shifted by a few pixels along the lines
    # (the feedback and the scanner's hysteresis), the frames match (a mirrored one would not)
    a, b = (im.z - im.z.mean() for im in (trace, retrace))
    match = {
        k: np.corrcoef(a[:, 20:-20].ravel(), b[:, 20 + k : 236 + k].ravel())[0, 1] for k in range(-15, 16)
    }
    best = max(match, key=match.get)
    assert match[best] > 0.9 and 1 <= abs(best) <= 10 and match[0] < match[best]


def test_a_pair_reads_each_key_as_its_direction_and_refuses_the_other(tmp_path):
    """A config's trace/retrace pair (``read_image_pair``): one .nid file under both keys gives
    its forward frame as the trace and its backward frame as the retrace, as the file's frames
    read one by one; a file whose own header records the other direction (the real Nanosurf text
    export, a backward scan) and one image under both keys are refused, naming the key."""
    rng = np.random.default_rng(2)
    frames = {
        f: {"Topography": rng.integers(-(2**15), 2**15, (6, 8))} for f in ("Scan forward", "Scan backward")
    }
    nid = str(write_nid(tmp_path / "pair.nid", frames))
    pair = lambda trace, retrace: type("Pair", (), {"trace": trace, "retrace": retrace})
    trace, retrace = read_image_pair(pair(nid, nid), tmp_path / "c.yaml", "data.scans.0")
    np.testing.assert_array_equal(trace.z, read_image(nid, direction="trace").z)
    np.testing.assert_array_equal(retrace.z, read_image(nid, direction="retrace").z)
    assert not np.array_equal(trace.z, retrace.z)
    text = str(GRATING_FILE)  # its header: a backward scan
    with pytest.raises(ValueError, match=r"data\.scans\.0\.trace: .*holds the retrace"):
        read_image_pair(pair(text, text), tmp_path / "c.yaml", "data.scans.0")
    tiff = tmp_path / "one.tif"
    tifffile.imwrite(tiff, rng.normal(size=(6, 8)))
    same = {"path": str(tiff), "size_nm": [4000.0, 3000.0]}
    with pytest.raises(ValueError, match=r"data\.scans\.0: the trace and the retrace are the same image"):
        read_image_pair(pair(same, same), tmp_path / "c.yaml", "data.scans.0")


def test_a_pair_takes_how_it_was_scanned_from_the_header_and_refuses_a_contradiction(tmp_path):
    """``scan_settings``: what a pair leaves out is what its files' header records (the real
    lattice's: ``Time/Line=2 s``, ``Rotation=-45 °``, ``Overscan=5 %``, ``Scan direction=Up``),
    else the schema's default; a value given against the header, trace and retrace headers that
    disagree, and a line rate nowhere, are refused naming the key and the header entry."""
    from jaxafm.config.calibrate import CalibrationPair
    from jaxafm.config.diagnose import ScanFiles

    config = tmp_path / "c.yaml"
    resolved = lambda **pair: scan_settings(
        (p := CalibrationPair(**pair)), read_image_pair(p, config, "data.scans.0"), config, "data.scans.0"
    )
    settings = lambda **pair: resolved(**pair)[0]
    real = {"trace": str(NID_FILE), "retrace": str(NID_FILE)}
    assert settings(**real) == {"line_rate_hz": 0.5, "angle_deg": -45.0, "overscan": 0.05, "lines": "up"}
    assert set(resolved(**real)[1].values()) == {"header"}
    assert resolved(**real, angle_deg=-45, line_rate_hz=0.5) == (
        settings(**real),
        {"line_rate_hz": "given", "angle_deg": "given", "overscan": "header", "lines": "header"},
    )
    for key, value, entry in [
        ("angle_deg", 0, "Rotation=-45 °"),
        ("overscan", 0.1, "Overscan=5 %"),
        ("line_rate_hz", 1.0, "Time/Line=2 s"),
        ("lines", "down", "Scan direction=Up"),
    ]:
        with pytest.raises(
            ValueError, match=rf"data\.scans\.0\.{key} = .*disagrees with .*{re.escape(entry)}"
        ):
            settings(**real, **{key: value})
    # a rate given with an image is named as the config gives it
    with pytest.raises(
        ValueError, match=r"data\.scans\.0\.trace\.line_rate_hz = 1\.0 disagrees.*remove trace\."
    ):
        settings(trace={"path": str(NID_FILE), "line_rate_hz": 1.0}, retrace=str(NID_FILE))
    frames = lambda seed: {
        f: {"Topography": np.random.default_rng([seed, i]).integers(-(2**15), 2**15, (6, 8))}
        for i, f in enumerate(("Scan forward", "Scan backward"))
    }
    other = ("Time/Line=500 ms", "Rotation=30 °", "Overscan=10 %")
    down = str(write_nid(tmp_path / "down.nid", frames(1), direction="Down", scan=other))
    assert settings(trace=down, retrace=down) == {
        "line_rate_hz": 2.0,
        "angle_deg": 30.0,
        "overscan": 0.1,
        "lines": "down",
    }
    odd = ("Time/Line=0.1667 s", "Rotation=-45 Deg", "Overscan=5")  # Overscan: per cent or a fraction?
    odd = str(write_nid(tmp_path / "odd.nid", frames(3), scan=odd))
    with pytest.raises(
        ValueError, match=r"data\.scans\.0: jaxafm cannot read overscan from the header .*Overscan=5\b"
    ):
        settings(trace=odd, retrace=odd)
    # given: it is used; a rate at the header's 4 digits and the same angle a turn on agree with it
    assert settings(trace=odd, retrace=odd, overscan=0.05, line_rate_hz=6.0, angle_deg=315) == {
        "line_rate_hz": 6.0,
        "angle_deg": 315.0,
        "overscan": 0.05,
        "lines": "up",
    }
    slower = str(
        write_nid(tmp_path / "slow.nid", frames(2), direction="Down", scan=("Time/Line=1 s", *other[1:]))
    )
    with pytest.raises(ValueError, match=r"data\.scans\.0: the trace's and the retrace's headers disagree"):
        settings(trace=down, retrace=slower)
    for name, z in (("t.tif", np.eye(6, 8)), ("r.tif", np.eye(6, 8)[::-1])):
        tifffile.imwrite(tmp_path / name, z)
    tiffs = {k: {"path": str(tmp_path / f"{k[0]}.tif"), "size_nm": [800, 600]} for k in ("trace", "retrace")}
    with pytest.raises(
        ValueError, match=r"data\.scans\.0: missing line_rate_hz: the files \(.*t\.tif and .*r\.tif\) do not"
    ):
        settings(**tiffs)
    assert resolved(**tiffs, line_rate_hz=1.0) == (
        {"line_rate_hz": 1.0, **CalibrationPair.SCAN_DEFAULTS},
        {"line_rate_hz": "given", "angle_deg": "default", "overscan": "default", "lines": "default"},
    )
    # turned a quarter (fast_axis: y), the header's angle and line order are the stored image's:
    # left out they are refused, given they are taken; the rate and the over-scan stay the header's
    turn = lambda f: {"path": f, "fast_axis": "y"}
    for name, other in (("angle_deg", {"lines": "up"}), ("lines", {"angle_deg": 120.0})):
        with pytest.raises(
            ValueError, match=rf"data\.scans\.0: the header's {name} .*down\.nid.*fast_axis: y"
        ):
            settings(trace=turn(down), retrace=turn(down), **other)
    assert resolved(trace=turn(down), retrace=turn(down), angle_deg=120.0, lines="up") == (
        {"line_rate_hz": 2.0, "angle_deg": 120.0, "overscan": 0.1, "lines": "up"},
        {"line_rate_hz": "header", "angle_deg": "given", "overscan": "header", "lines": "given"},
    )
    pair = ScanFiles(trace=down, retrace=down)  # jaxafm diagnose's pairs: a rate and an over-scan
    assert scan_settings(pair, read_image_pair(pair, config, "p"), config, "p")[0] == {
        "line_rate_hz": 2.0,
        "overscan": 0.1,
    }


def test_image_format_round_trips_exactly_and_never_overwrites(tmp_path):
    im = AFMImage(
        np.random.default_rng(0).normal(size=(5, 7)),
        (2.5, 4.0),
        (10.0, -3.0),
        {"source": "test", "line_rate_hz": 1.5},
    )
    path = save_image(im, tmp_path / "a.npz")
    back = load_image(path)
    assert np.array_equal(back.z, im.z) and back.pixel_size == im.pixel_size
    assert back.origin == im.origin and back.meta == im.meta
    # read as a file, with the scan settings it records as a header would (scan_settings reads them)
    scan = {"line_rate_hz": {"value": 1.5, "header": "meta line_rate_hz=1.5"}}
    assert read_image(path).meta == im.meta | {"scan": scan}
    with pytest.raises(FileExistsError, match="overwrite=True"):
        save_image(im, path)
    doc = json.loads(str(np.load(path)["meta_json"]))
    assert doc["format"] == "jaxafm-image" and doc["version"] == 1


def test_failed_save_leaves_the_existing_file_intact(tmp_path):
    good = AFMImage(np.ones((2, 2)), (1.0, 1.0), meta={"line_rate_hz": jnp.asarray(2.0)})  # JAX value: saved
    path = save_image(good, tmp_path / "a.npz")
    assert load_image(path).meta["line_rate_hz"] == 2.0
    bad = AFMImage(np.zeros((2, 2)), (1.0, 1.0), meta={"note": object()})
    with pytest.raises(TypeError):
        save_image(bad, path, overwrite=True)
    assert np.array_equal(load_image(path).z, np.ones((2, 2)))
    path.write_bytes(b"")
    with pytest.raises(ValueError, match="not a jaxafm image file"):
        load_image(path)


def test_image_format_refuses_other_npz_and_other_versions(tmp_path):
    np.savez(tmp_path / "other.npz", data=np.zeros(3))
    with pytest.raises(ValueError, match="not a jaxafm image file"):
        load_image(tmp_path / "other.npz")
    doc = {"format": "jaxafm-image", "version": 99, "pixel_size_nm": [1, 1], "origin_nm": [0, 0], "meta": {}}
    np.savez(tmp_path / "future.npz", z=np.zeros((2, 2)), meta_json=np.asarray(json.dumps(doc)))
    with pytest.raises(ValueError, match="version 99 is not supported"):
        load_image(tmp_path / "future.npz")


def test_tiff_needs_its_size_and_converts_units(tmp_path):
    z = np.arange(12, dtype=np.float32).reshape(3, 4) / 1000  # µm
    tifffile.imwrite(tmp_path / "h.tif", z)
    with pytest.raises(ValueError, match="size_nm"):
        read_image(tmp_path / "h.tif")
    im = read_image(tmp_path / "h.tif", size_nm=(400.0, 300.0), z_unit="um")
    np.testing.assert_allclose(im.z, z.astype(float) * 1000, rtol=1e-6)
    assert np.allclose(im.pixel_size, (100.0, 100.0))


def test_gwyddion_file_reads_non_square_images_in_nm(tmp_path):
    from gwyfile.objects import GwyContainer, GwyDataField, GwySIUnit

    z = np.arange(12.0).reshape(3, 4) * 1e-9  # m, 3 rows x 4 columns
    c = GwyContainer()
    c["/0/data/title"] = "Height"
    c["/0/data"] = GwyDataField(
        z, xreal=4e-6, yreal=3e-6, si_unit_xy=GwySIUnit(unitstr="m"), si_unit_z=GwySIUnit(unitstr="m")
    )
    c.tofile(str(tmp_path / "a.gwy"))
    im = read_image(tmp_path / "a.gwy")
    np.testing.assert_allclose(im.z, np.arange(12.0).reshape(3, 4)[::-1])  # Gwyddion's row 0 is the top line
    assert np.allclose(im.pixel_size, (1000.0, 1000.0)) and im.meta["channel"] == "Height"
    with pytest.raises(ValueError, match="no channel 'Phase'"):
        read_image(tmp_path / "a.gwy", channel="Phase")


def test_topostats_file_reads_through_afmreader(tmp_path):
    import h5py

    z = np.random.default_rng(1).normal(size=(6, 6))
    with h5py.File(tmp_path / "a.topostats", "w") as f:
        f["topostats_file_version"] = 0.2
        f["image"] = z
        f["pixel_to_nm_scaling"] = 2.5
    im = read_image(tmp_path / "a.topostats")
    np.testing.assert_allclose(im.z, z)
    assert im.pixel_size == (2.5, 2.5) and im.meta["reader"] == "AFMReader.topostats"


def test_scan_becomes_an_image_with_its_metadata(tmp_path):
    afm = default_afm()
    raster = Raster((2000.0, 1000.0), 8, 4, line_rate=2.0)
    scan = raster_scan(
        afm,
        Grating(jnp.asarray(500.0), jnp.asarray(50.0)),
        afm.initial_state(t0=7.0),
        raster,
        key=jax.random.key(0),
    )
    im = from_scan(scan, raster, "retrace")
    assert im.shape == (4, 8) and im.pixel_size == (250.0, 250.0)
    assert (
        im.meta["direction"] == "retrace" and im.meta["line_rate_hz"] == 2.0 and im.meta["start_time_s"] > 7.0
    )
    assert np.allclose(im.x, -1000 + 125 + 250 * np.arange(8))
    back = load_image(save_image(im, tmp_path / "scan.npz"))
    assert np.array_equal(back.z, im.z) and back.meta == im.meta


def test_a_saved_scan_is_read_back_with_how_it_was_scanned(tmp_path):
    """A pair jaxafm saved (``from_scan``, ``save_image``) needs no scan settings in the config:
    its line rate, angle, over-scan and line order are the raster's, from the files; one given
    against them is refused naming the file's entry."""
    from jaxafm.config.calibrate import CalibrationPair

    afm = default_afm()
    raster = Raster((2000.0, 1000.0), 8, 4, line_rate=2.5, overscan=0.05, direction="down", angle_deg=90.0)
    scan = raster_scan(
        afm,
        Grating(jnp.asarray(500.0), jnp.asarray(50.0)),
        afm.initial_state(),
        raster,
        key=jax.random.key(0),
    )
    files = {
        k: str(save_image(from_scan(scan, raster, k), tmp_path / f"{k}.npz")) for k in ("trace", "retrace")
    }
    config = tmp_path / "c.yaml"
    resolved = lambda **given: scan_settings(
        (p := CalibrationPair(**files, **given)), read_image_pair(p, config, "data"), config, "data"
    )
    assert resolved() == (
        {"line_rate_hz": 2.5, "angle_deg": 90.0, "overscan": 0.05, "lines": "down"},
        {k: "header" for k in ("line_rate_hz", "angle_deg", "overscan", "lines")},
    )
    with pytest.raises(ValueError, match=r"data\.overscan = 0\.1 disagrees with .*meta overscan=0\.05"):
        resolved(overscan=0.1)
    # the same files twice: the repeat, found from the files, names both scans
    from jaxafm.config import CalibrationImages, CalibrationLattice
    from jaxafm.jobs.calibrate import read_calibration

    twice = CalibrationImages(scans=[files, files])
    with pytest.raises(
        ValueError, match=r"line_rate_hz 2\.5 is given 2 times \(data\.scans\.0 and data\.scans\.1\)"
    ):
        read_calibration(twice, CalibrationLattice(pitch_nm=500.0), config, log=lambda *_: None)


@pytest.mark.parametrize(
    "content, suffix, error, match",
    [
        (None, ".txt", FileNotFoundError, "no such file"),
        ("just some notes\n1 2 3\n", ".txt", ValueError, "not a Nanosurf text export"),
        ("hello", ".png", ValueError, "unknown AFM image format '.png'"),
        ("not a tiff", ".tif", ValueError, "not a readable TIFF"),
        ("not a gwyddion file", ".gwy", ValueError, "not a readable Gwyddion file"),
    ],
)
def test_bad_files_are_named(tmp_path, content, suffix, error, match):
    path = tmp_path / f"f{suffix}"
    if content is not None:
        path.write_text(content)
    with pytest.raises(error, match=match) as info:
        read_image(path)
    assert str(path) in str(info.value)


def _nanosurf(tmp_path, values, width="2.00 μm", z_unit="nm", n=2):
    text = (
        f"Name : Topography_Fwd ({n}x{n})\n\nImage Width : {n}\nImage Height : {n}\n\n"
        f"Real Width : {width}\nReal Height : {width}\nZ Unit : {z_unit}\n\n" + " ".join(values) + "\n"
    )
    path = tmp_path / "scan.txt"
    path.write_text(text, encoding="utf-8")
    return path


def test_nanosurf_text_errors_name_the_problem(tmp_path):
    with pytest.raises(ValueError, match=r"pixels are NaN or inf \(first at row 0, column 1\)"):
        read_image(_nanosurf(tmp_path, ["1", "nan", "3", "4"]))
    with pytest.raises(ValueError, match="2 x 2 pixels but 3 values follow"):
        read_image(_nanosurf(tmp_path, ["1", "2", "3"]))
    with pytest.raises(ValueError, match="pixel size must be > 0 nm"):
        read_image(_nanosurf(tmp_path, ["1", "2", "3", "4"], width="0.00 μm"))
    with pytest.raises(ValueError, match="'Z Unit' = 'V'"):
        read_image(_nanosurf(tmp_path, ["1", "2", "3", "4"], z_unit="V"))
    im = read_image(_nanosurf(tmp_path, ["1", "2", "3", "4"], z_unit="um"))
    assert np.allclose(im.z, [[1000, 2000], [3000, 4000]]) and im.meta["direction"] == "trace"
    assert np.allclose(im.pixel_size, (1000.0, 1000.0))


def test_image_checks_its_own_values():
    with pytest.raises(ValueError, match="pixel size must be > 0 nm"):
        AFMImage(np.zeros((3, 3)), (0.0, 1.0))
    with pytest.raises(ValueError, match="at least 2 x 2 pixels"):
        AFMImage(np.zeros(5), (1.0, 1.0))


def test_real_image_becomes_a_sample_the_afm_can_scan():
    im = read_image(GRATING_FILE)
    sample = im.height_map()
    # at pixel centres the height map returns the measured pixels exactly
    rows, cols = np.array([0, 50, 127]), np.array([3, 64, 100])
    xy = np.stack([im.x[cols], im.y[rows]], axis=-1)
    np.testing.assert_allclose(sample.height(jnp.asarray(xy)), im.z[rows, cols], atol=1e-9)


# ---------------------------------------------------------------- image metadata from a config

Z_UM = np.arange(48.0).reshape(6, 8) / 8  # 6 lines of 8 px, µm: binary fractions, exact in nm


def _tiff(path: Path, z=Z_UM) -> Path:
    tifffile.imwrite(path, np.asarray(z, dtype=np.float32))  # no resolution tags, no unit
    return path


def _config(tmp_path: Path, doc: dict, schema):
    if schema.__name__ == "CalibrateConfig" and "data" in doc:  # measured images need the pitch
        doc = {"grating": {"pitch_nm": 1000.0}} | doc
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(doc, allow_unicode=True))
    return load_config(path, schema), path


def _read(tmp_path: Path, spec) -> AFMImage:
    """``spec`` as a config's image key, read as every mode reads it."""
    return read_image_file(ImageFile.model_validate(spec), tmp_path / "c.yaml", "image")


def test_tiff_pair_with_size_from_the_calibrate_config(tmp_path):
    from jaxafm.jobs.calibrate import read_calibration

    _tiff(tmp_path / "trace.tif")
    _tiff(tmp_path / "retrace.tif", Z_UM[:, ::-1])
    image = {"size_nm": [8000, 6000], "z_unit": "um"}
    data = {
        "trace": {"path": "trace.tif", **image},
        "retrace": {"path": "retrace.tif", "direction": "retrace", "line_rate_hz": 2.0, **image},
        "sensitivity_nm_per_v": [500.0, 500.0],
        "line_rate_hz": 2.0,
    }
    cfg, path = _config(tmp_path, {"data": data}, CalibrateConfig)
    (scan,) = read_calibration(cfg.data, cfg.grating, path)
    assert np.array_equal(np.asarray(scan.trace), Z_UM * 1000)
    assert np.array_equal(np.asarray(scan.retrace), Z_UM[:, ::-1] * 1000)
    assert scan.raster.size == (8000.0, 6000.0) and scan.raster.pixel_size == (1000.0, 1000.0)
    assert scan.raster.line_rate == 2.0


def test_measured_images_are_fitted_by_their_chords_unless_image_stages_are_asked_for(tmp_path):
    """On measured images step A's default is the chord stage alone (one for one scan): a list of
    step limits is counted against it; on the simulated AFM the two image stages follow; stages
    the user lists are fitted as listed."""
    _tiff(tmp_path / "t.tif")
    image = {"size_nm": [8000, 6000], "z_unit": "um"}
    pair = {
        "trace": {"path": "t.tif", **image},
        "retrace": {"path": "t.tif", "direction": "retrace", **image},
    }
    data = pair | {"sensitivity_nm_per_v": [500.0, 500.0], "line_rate_hz": 2.0}
    cfg, _ = _config(tmp_path, {"data": data, "solver": {"max_steps": [50]}}, CalibrateConfig)
    assert cfg.solver.image_blurs(measured=True) == ()
    with pytest.raises(ConfigError, match=r"solver.max_steps[\s\S]*1 stages here \(chords\)"):
        _config(tmp_path, {"data": data, "solver": {"max_steps": [50, 20, 10]}}, CalibrateConfig)
    asked = {"data": data, "solver": {"max_steps": [50, 20], "blur_px": [1.0]}}
    assert _config(tmp_path, asked, CalibrateConfig)[0].solver.image_blurs(measured=True) == (1.0,)
    simulated, _ = _config(tmp_path, {"simulate": {}, "solver": {"max_steps": [50, 20, 10]}}, CalibrateConfig)
    assert simulated.solver.image_blurs(measured=False) == (2.0, 1.0)


@pytest.mark.parametrize("fast_axis", ["x", "y"])
def test_tiff_grating_with_size_from_the_diagnose_config(tmp_path, fast_axis):
    """A 1-D grating of 16 px pitch over 128 px of 4096 nm: the diagnosis fits a 512 nm pitch.
    Stored with its lines as columns (fast_axis: y), it is transposed first."""
    from jaxafm.jobs.diagnose import run

    x = np.arange(128)
    z_um = np.where(x % 16 < 8, 0.0, 0.03) + np.random.default_rng(0).normal(0, 1e-4, (32, 128))
    _tiff(tmp_path / "g.tif", z_um if fast_axis == "x" else z_um.T)
    image = {"path": "g.tif", "size_nm": [4096, 1024], "z_unit": "um", "fast_axis": fast_axis}
    cfg, path = _config(tmp_path, {"image": image, "candidates": ["bow"], "max_steps": 5}, DiagnoseConfig)
    out = tmp_path / "out"
    run(cfg, path, Output(out), log=lambda line: None)
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["data"]["pixels"] == [32, 128] and doc["data"]["pixel_size_nm"] == [32.0, 32.0]
    assert doc["nominal"]["fitted"]["pitch"] == pytest.approx(512.0, abs=0.1)
    assert doc["nominal"]["fitted"]["phase_rise"] == pytest.approx(7.5 * 32, abs=0.5)  # edge at 7.5 px


def test_scans_read_their_pairs_through_the_config_keys(tmp_path):
    from jaxafm.jobs.diagnose import run

    _tiff(tmp_path / "t.tif")
    pair = {"trace": "t.tif", "retrace": {"path": "t.tif", "size_nm": [8000, 6000]}, "line_rate_hz": 1.0}
    scans = {"grating": {"pitch_nm": 400, "edge_width_nm": 20}, "pairs": [pair, pair]}
    cfg, path = _config(tmp_path, {"scans": scans}, DiagnoseConfig)
    with pytest.raises(ValueError, match=r"c.yaml: scans.pairs\[0\].trace: .*t.tif: .*give size_nm"):
        run(cfg, path, Output(tmp_path / "out"), log=lambda line: None)


def test_a_plain_path_still_names_an_image(tmp_path):
    scan = _nanosurf(tmp_path, ["1", "2", "3", "4"])
    for image in ("scan.txt", {"path": "scan.txt"}):
        cfg, path = _config(tmp_path, {"image": image}, DiagnoseConfig)
        im = read_image_file(cfg.image, path, "image")
        assert np.array_equal(im.z, [[1, 2], [3, 4]]) and im.meta["source"] == "scan.txt"
        assert im.meta == read_image(scan).meta | {"source": "scan.txt"}  # nothing given, nothing noted
    cfg, _ = _config(
        tmp_path,
        {"data": {"trace": "a.txt", "retrace": "b.txt", "sensitivity_nm_per_v": [1, 1], "line_rate_hz": 1}},
        CalibrateConfig,
    )
    assert cfg.data.trace == ImageFile(path="a.txt") and cfg.data.retrace.path == "b.txt"


def test_z_unit_converts_exactly_and_first_row_top_flips(tmp_path):
    _tiff(tmp_path / "h.tif")
    im = _read(tmp_path, {"path": "h.tif", "size_nm": [800, 600], "z_unit": "um"})
    assert np.array_equal(im.z, Z_UM * 1000) and im.pixel_size == (100.0, 100.0)
    assert im.meta["given"] == {"size_nm": [800.0, 600.0], "z_unit": "um"}
    top = _read(tmp_path, {"path": "h.tif", "size_nm": [800, 600], "z_unit": "um", "first_row": "top"})
    assert np.array_equal(top.z, Z_UM[::-1] * 1000) and "flipped" in top.meta["row_order"]
    nm = _read(tmp_path, {"path": "h.tif", "size_nm": [800, 600]})
    assert np.array_equal(nm.z, Z_UM) and "assumed" in nm.meta["converted"]  # no z_unit: nm


@pytest.mark.parametrize("first_row", ["bottom", "top"])
def test_fast_axis_y_turns_the_image_keeping_the_frame_right_handed(tmp_path, first_row):
    """Three marks on a stored image whose lines are its columns: ``o``, ``a`` a step up the
    columns (the way the trace runs), ``b`` a step to the right. Read with ``fast_axis: y`` the
    trace runs along +x, and the turn from ``a - o`` to ``b - o`` keeps its sense (a rotation; a
    transpose would reverse it). The size is of the turned image: along the lines first."""
    stored = np.zeros((8, 6))  # 6 lines (the columns) of 8 px
    marks = {"o": (2, 1), "a": (5, 1), "b": (2, 4)}  # (row, column), row 0 at the bottom
    for k, (i, j) in enumerate(marks.values(), start=1):
        stored[i, j] = k
    _tiff(tmp_path / "h.tif", stored if first_row == "bottom" else stored[::-1])
    im = _read(tmp_path, {"path": "h.tif", "size_nm": [800, 600], "fast_axis": "y", "first_row": first_row})
    assert im.shape == (6, 8) and im.pixel_size == (100.0, 100.0)
    at = {k: np.argwhere(im.z == v)[0][::-1] for k, v in zip(marks, (1, 2, 3))}  # (x, y) px
    up, right = at["a"] - at["o"], at["b"] - at["o"]
    assert up[0] == 3 and up[1] == 0  # the trace's way: +x
    stored_sense = np.sign(np.cross([0, 3], [3, 0]))  # (x, y) of a - o and b - o as stored
    assert np.sign(np.cross(up, right)) == stored_sense


def test_fast_axis_y_puts_every_pixel_where_the_turn_puts_its_point(tmp_path):
    """A saved image with an origin and unequal pixel sizes, read with ``fast_axis: y``: each
    value lies at (x', y') = (y, -x) of where it lay."""
    z = np.arange(35.0).reshape(5, 7)
    path = save_image(AFMImage(z, (2.5, 4.0), (10.0, -3.0), {"source": "test"}), tmp_path / "a.npz")
    im = _read(tmp_path, {"path": str(path), "fast_axis": "y"})
    position = lambda image, v: np.array(image.origin) + np.argwhere(image.z == v)[0][::-1] * image.pixel_size
    for v in (0.0, 6.0, 30.0, 17.0):
        x, y = position(load_image(path), v)
        np.testing.assert_allclose(position(im, v), (y, -x))


def test_gwyddion_row_order_from_the_config_wins_and_is_noted(tmp_path):
    from gwyfile.objects import GwyContainer, GwyDataField

    c = GwyContainer()
    c["/0/data/title"] = "Height"
    c["/0/data"] = GwyDataField(np.arange(12.0).reshape(3, 4) * 1e-9, xreal=4e-6, yreal=3e-6)
    c.tofile(str(tmp_path / "a.gwy"))
    im = _read(tmp_path, {"path": "a.gwy", "first_row": "bottom"})
    np.testing.assert_allclose(im.z, np.arange(12.0).reshape(3, 4))  # as stored: not flipped
    assert im.meta["file"] == {"first_row": "top"}


def test_a_scalar_size_giving_non_square_pixels_is_refused(tmp_path):
    _tiff(tmp_path / "h.tif")  # 8 px wide, 6 lines
    with pytest.raises(ValueError, match=r"non-square pixels") as info:
        _read(tmp_path, {"path": "h.tif", "size_nm": 8000})
    message = str(info.value)
    assert "[8000, 6000]" in message and "[10666.7, 8000]" in message
    assert "image" in message and "h.tif" in message and "c.yaml" in message
    square = _read(tmp_path, {"path": "h.tif", "size_nm": [8000, 6000]})
    assert square.pixel_size == (1000.0, 1000.0)


def test_a_size_that_disagrees_with_the_files_is_refused_beyond_one_percent(tmp_path):
    _nanosurf(tmp_path, ["1", "2", "3", "4"], width="2.00 μm")  # 2000 x 2000 nm
    near = _read(tmp_path, {"path": "scan.txt", "size_nm": 2010})  # 0.5 %: the config's is used
    assert near.size == (2010.0, 2010.0) and near.meta["file"] == {"size_nm": [2000.0, 2000.0]}
    with pytest.raises(
        ValueError, match=r"\[2100, 2100\] nm disagrees with the file's own size \[2000, 2000\]"
    ):
        _read(tmp_path, {"path": "scan.txt", "size_nm": 2100})


def test_a_z_unit_that_disagrees_with_the_files_is_refused(tmp_path):
    _nanosurf(tmp_path, ["1", "2", "3", "4"], z_unit="nm")
    assert np.array_equal(_read(tmp_path, {"path": "scan.txt", "z_unit": "nm"}).z, [[1, 2], [3, 4]])
    with pytest.raises(
        ValueError, match=r"image: .*scan.txt: z_unit = 'um' disagrees with the file's own height unit 'nm'"
    ):
        _read(tmp_path, {"path": "scan.txt", "z_unit": "um"})


def test_direction_and_line_rate_from_the_config_win_and_are_noted(tmp_path):
    _nanosurf(tmp_path, ["1", "2", "3", "4"])  # its name says Fwd: a trace
    im = _read(tmp_path, {"path": "scan.txt", "direction": "retrace", "line_rate_hz": 0.5})
    assert im.meta["direction"] == "retrace" and im.meta["line_rate_hz"] == 0.5
    assert im.meta["file"] == {"direction": "trace"}


def test_a_tiff_without_size_is_refused_naming_the_key(tmp_path):
    _tiff(tmp_path / "h.tif")
    with pytest.raises(ValueError, match=r"c.yaml: image: .*h.tif: .*give size_nm"):
        _read(tmp_path, "h.tif")


@pytest.mark.parametrize(
    "image, match",
    [
        ({"size_nm": float("nan")}, r"image.size_nm[^\n]*finite number \(got nan\)"),
        ({"size_nm": [8000, -1]}, r"image.size_nm[^\n]*greater than 0 \(got -1\)"),
        ({"size_nm": [1, 2, 3]}, r"image.size_nm: List should have at most 2 items"),
        ({"z_unit": "V"}, r"image.z_unit: Input should be 'pm', [^\n]*\(got 'V'\)"),
        ({"line_rate_hz": 0}, r"image.line_rate_hz: Input should be greater than 0"),
        ({"fast_axis": "z"}, r"image.fast_axis: Input should be 'x' or 'y' \(got 'z'\)"),
        ({"first_row": "left"}, r"image.first_row: Input should be 'bottom' or 'top'"),
        ({"direction": "up"}, r"image.direction: Input should be 'trace' or 'retrace'"),
        ({"size": 8000}, r"image.size: unknown key"),
    ],
)
def test_bad_image_metadata_is_refused_by_the_schema_naming_the_key(tmp_path, image, match):
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump({"image": {"path": "h.tif", **image}}))
    with pytest.raises(ConfigError, match=match):
        load_config(path, DiagnoseConfig)


@pytest.mark.parametrize(
    "trace, match",
    [
        ({"line_rate_hz": 4.0}, r"data: line_rate_hz = 2 Hz, trace.line_rate_hz = 4 Hz disagree"),
        ({"direction": "retrace"}, r"data: trace.direction is 'retrace', but the trace key holds"),
    ],
)
def test_a_pair_refuses_image_metadata_that_contradicts_it(tmp_path, trace, match):
    data = {
        "trace": {"path": "t.tif", **trace},
        "retrace": "r.tif",
        "sensitivity_nm_per_v": [500.0, 500.0],
        "line_rate_hz": 2.0,
    }
    with pytest.raises(ConfigError, match=match):
        _config(tmp_path, {"data": data}, CalibrateConfig)
    pair = {k: v for k, v in data.items() if k != "sensitivity_nm_per_v"}
    scans = {"grating": {"pitch_nm": 400, "edge_width_nm": 20}, "pairs": [pair, pair]}
    with pytest.raises(ConfigError, match=match.replace("data:", "scans.pairs.0:")):
        _config(tmp_path, {"scans": scans}, DiagnoseConfig)
