"""The compiled sample's binding: records are built from the C's own field tables and filled
by name, every field once; arrays are handed over only as the C reads them."""

import numpy as np
import pytest

from ddh_vsensor.estimator import kalman_step


def test_records_take_their_fields_from_the_c():
    names = kalman_step.field_names("filter")
    assert {"flow_scale", "referenced", "held", "was_stopped"} <= set(names)
    rec = kalman_step.record("filter", 3, **{**dict.fromkeys(names, 0),
                                             "flow_scale": [1.0, 2.0, 3.0]})
    assert rec["flow_scale"].tolist() == [1.0, 2.0, 3.0]
    assert rec.dtype["referenced"] == np.int32
    assert rec.dtype["flow_scale"] == np.float64


def test_a_field_missing_or_unknown_is_an_error_naming_it():
    names = kalman_step.field_names("filter")
    with pytest.raises(TypeError, match="held"):
        kalman_step.record("filter", 1, **{n: 0 for n in names if n != "held"})
    with pytest.raises(TypeError, match="flow_scal'"):
        kalman_step.record("filter", 1, **dict.fromkeys(names, 0), flow_scal=1.0)


def test_arrays_must_be_what_the_c_reads():
    with pytest.raises(ValueError, match="speed_rpm is float32"):
        kalman_step.pointers(speed_rpm=np.zeros((4, 2), dtype=np.float32))
    with pytest.raises(ValueError, match="not C-contiguous"):
        kalman_step.pointers(speed_rpm=np.zeros((2, 4)).T)
    with pytest.raises(ValueError, match="flagged is float64"):
        kalman_step.pointers(flagged=np.zeros((4, 2)))


def test_the_compiled_filter_holds_ten_switches_a_unit():
    assert (kalman_step.max_states() - 11) // 2 == 10
