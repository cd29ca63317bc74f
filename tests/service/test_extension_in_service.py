"""The service runs an extended model from 'analyze' when given one."""

from __future__ import annotations

from ddh_vsensor.estimator.extension import Extension, ExtendedEstimator
from ddh_vsensor.estimator.estimator import Estimator
from ddh_vsensor.service import Service, ServiceOptions


def test_service_builds_the_extended_estimator(cfg, unit_tables, tmp_path) -> None:
    ext = Extension("pump_leakage", {"leakage_factor": 1.5}, "boom", cfg.physics_hash())
    path = ext.save(tmp_path / "extension.json")
    loaded = Extension.load(path, cfg, "boom")
    service = Service(cfg, unit_tables, {"interface": "virtual", "channel": "ext-test"},
                      ServiceOptions(extensions={"boom": loaded}))
    boom, bucket = service.units["boom"].estimator, service.units["bucket"].estimator
    assert isinstance(boom, ExtendedEstimator) and isinstance(bucket, Estimator)
    # Motor stopped, load held: the leakier model lets the boom sink faster than nominal.
    nominal = Estimator(cfg, "boom", unit_tables["boom"])
    for est in (boom, nominal):
        est.preset(150.0, 0.5)
        for k in range(200):
            est.step(k * 0.01, 0.0, 22.0, 27.0)
    sink_ext, sink_nom = 150.0 - boom.position_mm, 150.0 - nominal.position_mm
    assert sink_nom > 0.0
    assert 1.4 < sink_ext / sink_nom < 1.6


def test_the_service_integrates_frames_through_the_extended_estimator(cfg, unit_tables,
                                                                      tmp_path) -> None:
    """The service steps its units with the Hall states and the time since which they hold:
    an extended estimator takes them as the plain one does (it once refused the call)."""
    from ddh_vsensor.canbus.dbc import FrameCodec
    ext = Extension("pump_leakage", {"leakage_factor": 1.5}, "boom", cfg.physics_hash())
    service = Service(cfg, unit_tables, {"interface": "virtual", "channel": "ext-test-2"},
                      ServiceOptions(extensions={"boom": ext}))
    codec, unit = FrameCodec(cfg), service.units["boom"]
    states = {a: {name: 0 for name in cfg.unit(a).references_mm} for a in cfg.unit_names}
    service.inputs.oil(codec.encode_oil_temp(30.0, 0.0), 0.0)
    for k in range(1, 60):
        t = k * 0.01
        states["boom"]["mid"] = int(k >= 30)
        service.inputs.io(codec.encode_inputs(states, t - 0.004), t)
        assert unit.integrate(codec.encode_sevcon("boom", 20.0, 1500.0, t), t)
    assert unit.estimator.referenced                    # the mid switch's edge was taken
