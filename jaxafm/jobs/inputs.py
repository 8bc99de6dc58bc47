"""The files a config names, read as the library's types: records, images and model files.
A relative path is relative to the config file (``builtin:NAME``: a shipped file); errors name
the config key as the user wrote it and the file."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from ..config import ImageFile, RecordData, resolve_data_path
from ..instrument.images import AFMImage, read_image
from ..instrument.records import Record, read_record
from ..model import io as model_io


def read_record_file(data: RecordData, config_path: Path, require_output: bool = True) -> Record:
    """The record a config's ``data`` key names, converted to s, V and nm
    (:func:`~jaxafm.instrument.records.read_record`; ``require_output=False``: inputs alone may do)."""
    spec = data.model_dump(exclude={"path"})
    return read_record(resolve_data_path(data.path, config_path), **spec, require_output=require_output)


def read_image_file(spec, config_path, key: str) -> AFMImage:
    """The image a config key names, with the key's metadata (:func:`~jaxafm.instrument.images.read_image`).

    Arguments:
        spec: the key's ``ImageFile``, or its path alone.
        config_path: the config file; a relative path is relative to it.
        key: the key as the user wrote it (``data.trace``), named in errors.

    Returns:
        The image; ``meta["source"]`` is the path as the config gives it.

    Raises:
        FileNotFoundError, ValueError: naming the config, the key, the file and the value.
    """
    spec = ImageFile.model_validate(spec)
    given = spec.model_dump(exclude={"path"}, exclude_none=True, exclude_unset=True)
    try:
        image = read_image(resolve_data_path(spec.path, config_path), **given)
    except (ValueError, FileNotFoundError) as e:
        raise type(e)(f"{config_path}: {key}: {e}") from None
    return dataclasses.replace(image, meta=image.meta | {"source": spec.path})


def read_image_pair(pair, config_path: Path, key: str) -> tuple:
    """The trace and the retrace image of a config's pair ``key`` (its keys ``trace`` and
    ``retrace``, :func:`read_image_file`), each read as the scan direction of its key: of a file
    that holds both (a Nanosurf .nid), that frame.

    Raises:
        ValueError: naming the config and the key: a file whose own header records the other
            direction, or one image under both keys.
    """
    images = []
    for k in ("trace", "retrace"):
        # a direction given is already the key's (ImagePair refuses another)
        given = ImageFile.model_validate(getattr(pair, k)).model_dump(exclude_unset=True)
        image = read_image_file(given | {"direction": k}, config_path, f"{key}.{k}")
        recorded = image.meta.get("file", {}).get("direction")
        if recorded in ("trace", "retrace"):
            raise ValueError(
                f"{config_path}: {key}.{k}: {given['path']} holds the {recorded} (its own header says so), "
                f"not the {k}: swap the two files"
            )
        images.append(image)
    trace, retrace = images
    if np.array_equal(trace.z, retrace.z):
        raise ValueError(
            f"{config_path}: {key}: the trace and the retrace are the same image ({trace.meta['source']}); "
            "step A needs both directions of each line"
        )
    return trace, retrace


def scan_settings(pair, images: tuple, config_path: Path, key: str) -> tuple:
    """How a config's pair ``key`` was scanned: its ``line_rate_hz`` and the settings of its
    ``SCAN_DEFAULTS`` (``angle_deg``, ``overscan``, ``lines``; those its schema has), each as
    the config gives it, else as the images' own header records it (``meta["scan"]``: a Nanosurf
    .nid file's ``Time/Line``, ``Rotation``, ``Overscan``, ``Scan direction``), else its default.

    Arguments:
        pair: the config's ``ImagePair``.
        images: its (trace, retrace) ``AFMImage`` s, as :func:`read_image_pair` reads them.
        config_path, key: named in errors (``data.scans.0``).

    Returns:
        ``({setting: value}, {setting: "given", "header" or "default"})``, every setting of the pair.

    Raises:
        ValueError: naming the config, the key, the values and the header entry: a given setting
            that disagrees with the header's, trace and retrace headers that disagree, no line
            rate anywhere, or an angle or line order left to the header of an image that
            ``fast_axis: y`` turns (the header's are the stored image's, :data:`TURNED`).
    """
    out, source = {}, {}
    files = " and ".join(im.meta["source"] for im in images)
    turned = any("fast_axis" in im.meta for im in images)
    header = [(im.meta["source"], im.meta.get("scan", {})) for im in images]
    # each setting's key as the config gives it and its value there (a rate: the pair's or an image's)
    givens = [next(iter(pair.given_line_rates.items()), ("line_rate_hz", None))]
    givens += [(name, getattr(pair, name)) for name in type(pair).SCAN_DEFAULTS]
    for name, (written, given) in zip(("line_rate_hz", *type(pair).SCAN_DEFAULTS), givens):
        recorded = {source: scan[name] for source, scan in header if name in scan}
        unread = [f"{f}: {r['header']}" for f, r in recorded.items() if "unread" in r]
        if unread and given is None:
            raise ValueError(
                f"{config_path}: {key}: jaxafm cannot read {name} from the header ({'; '.join(unread)}): "
                f"give {name}"
            )
        recorded = {f: r for f, r in recorded.items() if "value" in r}
        said = "; ".join(f"{source}: {r['header']}, {name} {r['value']!r}" for source, r in recorded.items())
        if turned and name in TURNED and recorded:
            if given is None:
                raise ValueError(
                    f"{config_path}: {key}: the header's {name} ({said}) is the stored image's, before "
                    f"the quarter turn fast_axis: y makes: give {name} for the turned image"
                )
            recorded = {}  # the given one is the turned image's; the header's is not comparable
        values = [r["value"] for r in recorded.values()]
        if any(not _same(v, values[0], name) for v in values):
            raise ValueError(f"{config_path}: {key}: the trace's and the retrace's headers disagree ({said})")
        if given is not None and values and not _same(given, values[0], name):
            raise ValueError(
                f"{config_path}: {key}.{written} = {given!r} disagrees with the header ({said}): "
                f"remove {written} to use the header's"
            )
        value = given if given is not None else values[0] if values else type(pair).SCAN_DEFAULTS.get(name)
        if value is None:
            raise ValueError(
                f"{config_path}: {key}: missing line_rate_hz: the files ({files}) do not record how many "
                "lines (trace + retrace) a second were scanned; give it, Hz"
            )
        out[name] = value
        source[name] = "given" if given is not None else "header" if values else "default"
    return out, source


def settings_line(key: str, how: dict, source: dict) -> str:
    """How the pair ``key`` was scanned and where each setting came from, for the run's log
    (:func:`scan_settings`' two dicts)."""
    return f"{key}: scanned " + ", ".join(f"{k} {v} ({source[k]})" for k, v in how.items())


#: the scan settings a header records of the image as stored that a quarter turn (``fast_axis: y``)
#: changes: the line direction's angle, and which line came first
TURNED = ("angle_deg", "lines")


def _same(a, b, name: str) -> bool:
    """Equal: numbers to the 4 significant digits a header prints, ``angle_deg`` modulo 360."""
    if not isinstance(a, float | int):
        return a == b
    turns = (-360, 0, 360) if name == "angle_deg" else (0,)
    return any(math.isclose(a + turn, b, rel_tol=5e-4, abs_tol=1e-3) for turn in turns)


def read_model_and_posterior(spec: str, config_path: Path, key: str = "model") -> tuple:
    """The model file a config key names: ``(model, about, posterior, path)``
    (:func:`~jaxafm.model.io.read_model_and_posterior`).

    Raises:
        ValueError: naming the key and the file.
    """
    path = resolve_data_path(spec, config_path)
    try:
        return (*model_io.read_model_and_posterior(path), path)
    except (OSError, ValueError) as e:
        raise ValueError(f"{key}: {e}") from None


def read_model(spec: str, config_path: Path, key: str = "model") -> tuple:
    """The model file a config key names: ``(model, about, path)``
    (:func:`~jaxafm.model.io.read_model_file`).

    Raises:
        ValueError: naming the key and the file.
    """
    model, about, _, path = read_model_and_posterior(spec, config_path, key)
    return model, about, path
