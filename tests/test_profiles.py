"""Lens profiles: the shipped ones load, bad files give errors naming the key and file."""

import pytest

from pipeline.errors import InputError
from pipeline.io.profiles import available_lenses, lens_to_toml, load_lens


def test_paper_setups_ship():
    names = available_lenses()
    for expected in (
        "fujinon-12.5mm-f1.4-sony-1-3in",
        "fujinon-9mm-f1.4-sony-1-3in",
        "fujinon-12.5mm-f1.4-micron-1-2.5in",
        "sigma-30mm-f1.4-canon-eos-20d",
    ):
        assert expected in names
    for name in names:
        lens = load_lens(name)
        assert lens.aperture_mm == pytest.approx(lens.focal_length_mm / lens.f_number)


def test_rolling_profile_readout_is_70ms():
    lens = load_lens("fujinon-12.5mm-f1.4-micron-1-2.5in")
    assert lens.shutter == "rolling"
    assert lens.readout_time_s == pytest.approx(0.070, abs=1e-4)


def test_round_trip_through_toml(tmp_path):
    lens = load_lens("fujinon-12.5mm-f1.4-micron-1-2.5in")
    path = tmp_path / "copy.toml"
    path.write_text(lens_to_toml(lens))
    again = load_lens(path)
    for field in ("focal_length_mm", "f_number", "pixel_pitch_um", "line_time_us", "shutter"):
        assert getattr(again, field) == getattr(lens, field)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("focal_length_mm = 12.5\nf_number = 1.4\nzoom = 2\n", "unknown key 'zoom'"),
        (
            "f_number = 1.4\n[sensor]\npixel_pitch_um=4\nwidth_px=4\nheight_px=4\n",
            "focal_length_mm",
        ),
        (
            "focal_length_mm = 12.5\nf_number = 1.4\n[sensor]\npixel_pitch_um=4\nwidth_px=4\n",
            "height_px",
        ),
        (
            "focal_length_mm = 12.5\nf_number = 0\n[sensor]\npixel_pitch_um=4\nwidth_px=4\n"
            "height_px=4\n",
            "f_number",
        ),
        (
            "focal_length_mm = 12.5\nf_number = 2\n[sensor]\npixel_pitch_um=4\nwidth_px=4\n"
            "height_px=4\ncolour='red'\n",
            "colour",
        ),
        ("focal_length_mm = [\n", "TOML"),
    ],
)
def test_bad_profiles_name_key_and_file(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as info:
        load_lens(path)
    assert "bad.toml" in str(info.value)


def test_unknown_profile_lists_the_known_ones():
    with pytest.raises(InputError, match=r"fujinon-12\.5mm"):
        load_lens("no-such-lens")
