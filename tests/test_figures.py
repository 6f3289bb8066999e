"""make_figures writes one non-blank PNG per reproduced paper figure."""

from pathlib import Path

from mpa_gym.figures import make_figures

EXPECTED = [
    "fig03_inputs_pf_const.png",
    "fig04a_initial_error.png",
    "fig04b_impulse.png",
    "fig04c_gamma_mismatch.png",
    "fig04d_mass_mismatch.png",
    "fig08a_mode1.png",
    "fig08b_mode2.png",
    "fig08c_mode3.png",
    "fig09_stiffness_sweep.png",
    "fig11_kmax_kmin.png",
    "fig12_inputs_kmax_kmin.png",
    "fig14_load_1kg_kmax_vs_kmin.png",
]


def test_make_figures_writes_every_png(tmp_path: Path) -> None:
    out = tmp_path / "figs"  # not created yet: make_figures must create it
    paths = make_figures(out)
    assert [p.name for p in paths] == EXPECTED
    for name in EXPECTED:
        path = out / name
        assert path.is_file(), f"{name} was not written"
        data = path.read_bytes()
        assert data.startswith(b"\x89PNG"), f"{name} is not a PNG"
        assert len(data) > 10_000, f"{name} is only {len(data)} bytes: blank figure?"
