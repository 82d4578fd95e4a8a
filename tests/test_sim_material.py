"""Material units, presets re-fitted from the measured fabrics, JSON round trip."""

from pathlib import Path

import pytest

from physavatar.sim.material import PRESET_SOURCES, PRESETS, Material, fit_isotropic_membrane

FABRICS = Path("/work/shared/data/materials")


def test_isotropic_fit_recovers_an_isotropic_tensor():
    ks, nu = 120.0, 0.3
    a = ks / (1 - nu**2)
    assert fit_isotropic_membrane(a, nu * a, a, (1 - nu) * a / 2) == pytest.approx((ks, nu), rel=1e-3)


@pytest.mark.skipif(not FABRICS.exists(), reason="measured fabrics not available")
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_are_the_fit_of_their_fabric(name):
    fit = Material.from_arcsim(FABRICS / f"{PRESET_SOURCES[name]}.json")
    p = PRESETS[name]
    assert p.density == pytest.approx(fit.density)
    assert p.stretch_stiffness == pytest.approx(fit.stretch_stiffness, rel=1e-4)
    assert p.bend_stiffness == pytest.approx(fit.bend_stiffness, rel=1e-4)
    assert p.poisson == pytest.approx(fit.poisson)


def test_presets_are_ordered_light_to_stiff():
    s, c, d = PRESETS["silk"], PRESETS["cotton"], PRESETS["denim"]
    assert s.density < c.density < d.density
    assert d.bend_stiffness > max(s.bend_stiffness, c.bend_stiffness)


def test_codim_ipc_mapping_and_json_round_trip(tmp_path):
    m = Material.from_codim_ipc(400.0, 2.0, 3.0)
    assert m.density == pytest.approx(400 * 0.328e-3)
    assert m.stretch_stiffness == pytest.approx(0.076e6 * 0.328e-3 * 2.0)
    assert m.bend_stiffness == pytest.approx(0.076e6 * 0.328e-3**3 / (12 * (1 - 0.071**2)) * 3.0)
    m.save(tmp_path / "m.json")
    assert Material.load(tmp_path / "m.json") == m
    assert m.scaled(2.0).stretch_ratio == pytest.approx(m.stretch_ratio)


def test_load_reads_fit_physics_output_and_names_the_file_on_bad_input(tmp_path):
    import json

    from physavatar.errors import PhysavatarError

    m = Material(density=0.2, stretch_stiffness=40.0, bend_stiffness=3e-5, poisson=0.2, integrator="bdf2")
    (tmp_path / "fit.json").write_text(json.dumps({"material": m.to_dict(), "ratios": {}, "loss": 1.0}))
    assert Material.load(tmp_path / "fit.json") == m  # fit-physics' material.json, integrator included
    old = {k: v for k, v in m.to_dict().items() if k != "integrator"}  # written before the field existed
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert Material.load(tmp_path / "old.json").integrator == "euler"
    for name, text in (("list.json", "[1, 2]"), ("keys.json", '{"density": 0.2, "stiff": 1}'),
                       ("neg.json", '{"density": -1}'), ("rk4.json", '{"integrator": "rk4"}'), ("bad.json", "{")):
        (tmp_path / name).write_text(text)
        with pytest.raises(PhysavatarError) as e:
            Material.load(tmp_path / name)
        assert name in str(e.value)
