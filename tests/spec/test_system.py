"""System specs: built-ins, validation messages, Jacobians against autograd, n x p generality."""

from __future__ import annotations

import pytest
import torch

from certify.errors import SpecError
from certify.spec.system import System, builtin_names, load_system

from ..conftest import SPEC_3X2


def test_builtins_listed_and_loaded():
    assert {"vdp", "duffing"} <= set(builtin_names())
    vdp = load_system("vdp")
    assert (vdp.n, vdp.p, vdp.lam) == (2, 1, 2.5)
    assert vdp.X.tolist() == [[-2, 2], [-3, 3]] and vdp.Y.tolist() == [[-2, 2]]
    assert vdp.h_is_linear


@pytest.mark.parametrize("name", ["vdp", "duffing", "three"])
def test_symbolic_jacobians_match_autograd(name, system3):
    system = system3 if name == "three" else load_system(name)
    torch.manual_seed(1)
    lo = torch.as_tensor(system.X[:, 0])
    hi = torch.as_tensor(system.X[:, 1])
    x = lo + (hi - lo) * torch.rand(7, system.n, dtype=torch.float64)
    Jf = system.jac_f(x)
    Jh = system.jac_h(x)
    for i in range(len(x)):
        ref_f = torch.autograd.functional.jacobian(lambda v: system.f(v[None])[0], x[i])
        ref_h = torch.autograd.functional.jacobian(lambda v: system.h(v[None])[0], x[i])
        torch.testing.assert_close(Jf[i], ref_f, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(Jh[i], ref_h, rtol=1e-12, atol=1e-12)


def test_vdp_values():
    vdp = load_system("vdp")
    x = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    assert vdp.f(x).tolist() == [[2.0, -1.0 + 2.0 * 0.0]]
    assert vdp.jac_f(x).tolist() == [[[0.0, 1.0], [-1.0 - 2 * 1 * 2, 0.0]]]


def _mutate(old: str, new: str) -> str:
    assert old in SPEC_3X2
    return SPEC_3X2.replace(old, new)


@pytest.mark.parametrize("text,fragment", [
    (_mutate('X = [[-1, 1], [-1.5, 1.5], [-1, 1]]', 'X = [[-1, 1], [1.5, -1.5], [-1, 1]]'),
     "box X row 1 is empty or inverted"),
    (_mutate('X = [[-1, 1], [-1.5, 1.5], [-1, 1]]', 'X = [[-1, 1], [1, 1], [-1, 1]]'),
     "empty or inverted"),
    (_mutate('Y = [[-1.2, 1.2], [-1.3, 1.3]]', 'Y = [[-1.2, 1.2]]'), "box Y must have 2 rows"),
    (_mutate('"-2*c + a*b"', '"-2*c + a*q"'), "f[2]: uses unknown name 'q'"),
    (_mutate('"-2*c + a*b"', '"os.system(1)"'), "f[2]"),
    (_mutate('h = ["a", "c + 0.1*a"]', 'h = ["a"]'), "h has 1 entries for 2 outputs"),
    (_mutate("lam = 0.5", "lam = -1"), "design lam must be a finite number > 0; got -1"),
    (_mutate("lam = 0.5", "lam = inf"), "design lam must be a finite number > 0; got inf"),
    (_mutate("lam = 0.5", "lam = nan"), "design lam must be a finite number > 0"),
    (_mutate("lam = 0.5", "lam = true"), "design lam must be a finite number > 0"),
    (_mutate("lam = 0.5", "lam = 1e300"), "design lam must be at most 1e+12"),
    (_mutate("P = [[2, 0.1, 0], [0.1, 1, 0], [0, 0, 1]]", "P = [[1, 2, 0], [2, 1, 0], [0, 0, 1]]"),
     "positive definite"),
    (_mutate('name = "three"', ""), "missing field 'name'"),
    ("name = [", "not valid TOML"),
])
def test_malformed_specs_are_refused(text, fragment):
    with pytest.raises(SpecError) as err:
        System.from_text(text, origin="spec bad.toml")
    assert fragment in str(err.value)
    assert str(err.value).startswith("spec bad.toml")


def test_unknown_system_and_missing_file(tmp_path):
    with pytest.raises(SpecError, match="unknown system 'nosuch'"):
        load_system("nosuch")
    with pytest.raises(SpecError, match="not found"):
        load_system(str(tmp_path / "missing.toml"))


def test_spec_from_user_path(tmp_path):
    path = tmp_path / "three.toml"
    path.write_text(SPEC_3X2)
    s = load_system(str(path))
    assert (s.n, s.p) == (3, 2)
    assert s.f(torch.zeros(4, 3, dtype=torch.float64)).shape == (4, 3)
    assert s.jac_h(torch.zeros(4, 3, dtype=torch.float64)).shape == (4, 2, 3)
