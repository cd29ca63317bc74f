"""Setting known keys in the user's own configuration text: nothing else of the file moves."""

from __future__ import annotations

import pytest
import yaml

from ddh_vsensor.commission.yaml_text import Setting, set_values
from ddh_vsensor.errors import UserError

TEXT = """\
# my machine
units:
  boom:   # the big one
    references_mm: {bottom: 0.0, mid: 155.0}   # from the drawing
    reference_window_mm: 3.0            # datasheet
    reference_hysteresis_mm: 0.5
    stroke_mm: 311.15                   # untouched
"""


def test_values_and_comments_are_set_and_the_rest_is_kept() -> None:
    out = set_values(TEXT, "m.yaml", [
        Setting(("units", "boom", "references_mm", "mid"), "157.40", "commissioned: mid"),
        Setting(("units", "boom", "references_mm", "bottom"), None, "not commissioned"),
        Setting(("units", "boom", "reference_window_mm"), "2.00", "commissioned: w"),
        Setting(("units", "boom", "reference_tolerance_mm"), "0.08", "commissioned: tol",
                after="reference_hysteresis_mm")])
    lines = out.splitlines()
    assert lines[:3] == TEXT.splitlines()[:3]
    assert lines[3] == ("    references_mm: {bottom: 0.0, mid: 157.40}  "
                        "# commissioned: mid; not commissioned")
    assert lines[4] == "    reference_window_mm: 2.00           # commissioned: w"
    assert lines[5] == "    reference_hysteresis_mm: 0.5"
    assert lines[6] == "    reference_tolerance_mm: 0.08  # commissioned: tol"
    assert lines[7] == TEXT.splitlines()[6]
    boom = yaml.safe_load(out)["units"]["boom"]
    assert boom["references_mm"] == {"bottom": 0.0, "mid": 157.4}
    assert (boom["reference_window_mm"], boom["reference_tolerance_mm"]) == (2.0, 0.08)


def test_windows_line_endings_stay() -> None:
    out = set_values(TEXT.replace("\n", "\r\n"), "m.yaml", [
        Setting(("units", "boom", "reference_window_mm"), "2.00", "c")])
    assert out.count("\r\n") == TEXT.count("\n")
    assert yaml.safe_load(out)["units"]["boom"]["reference_window_mm"] == 2.0


@pytest.mark.parametrize("setting", [
    Setting(("units", "bucket", "reference_window_mm"), "2.00", "c"),
    Setting(("units", "boom", "reference_tolerance_mm"), "1.00", "c"),       # nowhere to go
    Setting(("units", "boom", "references_mm"), "1.00", "c"),                # not a number
])
def test_a_file_that_cannot_take_a_setting_is_one_user_error(setting: Setting) -> None:
    with pytest.raises(UserError):
        set_values(TEXT, "m.yaml", [setting])
