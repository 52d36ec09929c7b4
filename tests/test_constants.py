"""The shared constants (comest_bayes.constants) against their definitions, and one home for each."""

import math
import re
import tokenize

import pytest
from scipy import optimize

from comest_bayes.constants import FWHM_PER_SIGMA
from conftest import REPO_ROOT


def test_fwhm_per_sigma_is_the_full_width_at_half_maximum_of_a_unit_gaussian():
    half = optimize.brentq(lambda x: math.exp(-0.5 * x * x) - 0.5, 0.1, 3.0, xtol=1e-15)
    assert FWHM_PER_SIGMA == pytest.approx(2.0 * half, rel=1e-14)
    assert FWHM_PER_SIGMA == pytest.approx(2.3548200450309493, rel=1e-15)
    assert isinstance(FWHM_PER_SIGMA, float)


def _code(path) -> str:
    """The source of a module without its comments and strings (docstrings may quote the value)."""
    with open(path, "rb") as fh:
        kept = [tok.string for tok in tokenize.tokenize(fh.readline)
                if tok.type not in (tokenize.COMMENT, tokenize.STRING, tokenize.ENCODING)]
    return " ".join(kept)


def test_no_module_of_the_package_computes_its_own_fwhm_per_sigma():
    # 2 sqrt(2 ln 2) written out, or its decimal value, in the code of any module but constants.py
    pattern = re.compile(r"2(\.0)?\s*\*\s*(np\s*\.\s*|math\s*\.\s*)?sqrt\s*\(\s*2(\.0)?\s*\*\s*"
                         r"(np\s*\.\s*|math\s*\.\s*)?log\s*\(\s*2(\.0)?\s*\)\s*\)|2\.3548")
    found = [str(p.relative_to(REPO_ROOT)) for p in sorted((REPO_ROOT / "comest_bayes").rglob("*.py"))
             if p.name != "constants.py" and pattern.search(_code(p))]
    assert found == []
    # the pattern does find the expression as tokenised (the check is not vacuous)
    assert pattern.search(_code(REPO_ROOT / "comest_bayes" / "constants.py"))
