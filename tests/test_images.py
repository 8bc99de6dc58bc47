"""AFM images: the real Nanosurf grating, TIFF, Gwyddion and TopoStats files, the jaxafm
image format, scans as images, and bad input."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxafm
from jaxafm.instrument.afm import Raster, default_afm, raster_scan
from jaxafm.instrument.images import (
    AFMImage,
    from_scan,
    load_image,
    read_image,
    save_image,
)
from jaxafm.instrument.samples import Grating

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
    assert read_image(path).meta == im.meta
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
    import tifffile

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
