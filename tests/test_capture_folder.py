"""The capture folder (CONTRACT.md section 4): round trip and every bad-capture error."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tdfd.capture import CaptureFolderError, read_folder, write_frame
from tdfd.errors import InputError


def _raw(seed: int = 0, shape=(64, 64), lo=200, hi=3800) -> np.ndarray:
    return np.random.default_rng(seed).integers(lo, hi, shape).astype(np.uint16)


def test_round_trip_keeps_values_and_unknown_keys(tmp_path) -> None:
    raw = _raw()
    write_frame(tmp_path, "a", raw, lens_power_dpt=1.7, white_level=4095, distance_m=0.5, pair="p", exposure_s=0.01,
                temperature_c=31.5, time_s=12.0, operator="me")
    write_frame(tmp_path, "b", raw, lens_power_dpt=2.7, white_level=4095, distance_m=0.5, pair="p")
    write_frame(tmp_path, "s", (raw // 16).astype(np.uint8), lens_power_dpt=0.25)
    a, b, s = read_folder(tmp_path)
    assert np.array_equal(a.image, raw / 4095.0)
    assert a.metadata.distance_m == 0.5 and a.metadata.pair == "p" and a.metadata.temperature_c == 31.5
    assert a.metadata.extra == {"operator": "me"}
    assert json.loads((tmp_path / "a.json").read_text())["operator"] == "me"
    assert s.metadata.pair is None and s.metadata.white_level is None
    assert np.array_equal(s.image, (raw // 16) / 255.0)  # default white level: the PNG's full scale


def test_missing_sidecar_names_the_frame(tmp_path) -> None:
    write_frame(tmp_path, "a", _raw(), lens_power_dpt=1.0)
    (tmp_path / "a.json").unlink()
    with pytest.raises(CaptureFolderError, match=r"a\.png: no sidecar a\.json"):
        read_folder(tmp_path)


@pytest.mark.parametrize("text, match", [
    ("{not json", r"a\.json: malformed sidecar"),
    ('["lens_power_dpt"]', r"a\.json: the sidecar must be a JSON object"),
    ('{"distance_m": 0.5}', r"a\.json: the sidecar lacks the required key 'lens_power_dpt'"),
    ('{"lens_power_dpt": "1.5"}', r"a\.json: 'lens_power_dpt' must be a finite number"),
    ('{"lens_power_dpt": NaN}', r"a\.json: 'lens_power_dpt' must be a finite number"),
    ('{"lens_power_dpt": 1, "distance_m": -2}', r"a\.json: 'distance_m' must be > 0"),
    ('{"lens_power_dpt": 1, "pair": 3}', r"a\.json: 'pair' must be a string"),
    ('{"lens_power_dpt": 1, "white_level": 100000}', r"a\.json: white_level 100000 exceeds"),
    ('{"lens_power_dpt": 1, "white_level": 1000}', r"a\.png: raw value \d+ above white_level 1000"),
])
def test_malformed_sidecars(tmp_path, text: str, match: str) -> None:
    write_frame(tmp_path, "a", _raw(), lens_power_dpt=1.0)
    (tmp_path / "a.json").write_text(text)
    with pytest.raises(CaptureFolderError, match=match):
        read_folder(tmp_path)


def test_saturated_and_black_frames(tmp_path) -> None:
    raw = _raw()
    raw[:8] = 4095  # 12.5 % of the pixels at the white level
    write_frame(tmp_path / "sat", "hot", raw, lens_power_dpt=1.0, white_level=4095)
    with pytest.raises(CaptureFolderError, match=r"hot\.png: saturated frame"):
        read_folder(tmp_path / "sat")
    write_frame(tmp_path / "blk", "dark", _raw(lo=60, hi=70), lens_power_dpt=1.0, white_level=4095)
    with pytest.raises(CaptureFolderError, match=r"dark\.png: black frame"):
        read_folder(tmp_path / "blk")


def test_frames_of_different_sizes(tmp_path) -> None:
    write_frame(tmp_path, "a", _raw(), lens_power_dpt=1.0)
    write_frame(tmp_path, "b", _raw(shape=(64, 80)), lens_power_dpt=1.5)
    with pytest.raises(CaptureFolderError, match=r"b\.png: size 80x64 differs from a\.png \(64x64\)"):
        read_folder(tmp_path)


def test_pair_tags_need_two_frames_at_two_powers(tmp_path) -> None:
    write_frame(tmp_path, "a", _raw(), lens_power_dpt=1.0, pair="x")
    with pytest.raises(CaptureFolderError, match="pair 'x' has 1 frames"):
        read_folder(tmp_path)
    write_frame(tmp_path, "b", _raw(), lens_power_dpt=1.0, pair="x")
    with pytest.raises(CaptureFolderError, match="same lens power"):
        read_folder(tmp_path)


def test_bad_inputs(tmp_path) -> None:
    with pytest.raises(CaptureFolderError, match="not a folder"):
        read_folder(tmp_path / "nope")
    with pytest.raises(CaptureFolderError, match="no PNG frames"):
        read_folder(tmp_path)
    (tmp_path / "x.png").write_bytes(b"not a png")
    (tmp_path / "x.json").write_text('{"lens_power_dpt": 1}')
    with pytest.raises(CaptureFolderError, match=r"x\.png: not a readable PNG"):
        read_folder(tmp_path)
    with pytest.raises(CaptureFolderError, match="uint8 or uint16"):
        write_frame(tmp_path, "f", np.zeros((8, 8), np.float32), lens_power_dpt=1.0)
    assert issubclass(CaptureFolderError, InputError)
