"""The verdict is honest about its own test (issue 43 item 3): "at the noise level" only
where the combined test accepts; a library fit that lowers the misfit but still fails the
test is `partly_explained`, never named as the missing effect."""

from types import SimpleNamespace

from jaxwear._analyses.diagnose._stats import ALPHA
from jaxwear._analyses.diagnose._stats import Tests as _Tests
from jaxwear._analyses.diagnose._text import _partly_text, noise_claim, p_text
from jaxwear._analyses.diagnose._verdict import verdict_status


def _tests(p_chi2, p_autocorr=0.5, p_score=1.0):
    # the combined p is Bonferroni over three tests: 3 min(p)
    return _Tests(rmse_um=0.316, noise_um=0.306, ratio=1.07, p_chi2=p_chi2, rho=0.05,
                 z_autocorr=1.0, p_autocorr=p_autocorr, p_score=p_score)


def test_a_fit_whose_test_rejects_is_partly_explained_and_never_at_noise_level():
    # issue 43's case: the RMSE fell from 0.47 to 0.316 µm (noise 0.306) with a pair of
    # library effects, and the combined test rejects: 3 x 1e-4 = 3e-4 < α
    rejects = _tests(1e-4)
    assert rejects.systematic and rejects.p_min < ALPHA
    assert verdict_status(rejects, lowers=True) == "partly_explained"
    claim = noise_claim(rejects)
    assert "noise level" not in claim and "rejects" in claim
    fit = SimpleNamespace(rmse=0.316, label="speed_dependence+creep")
    diag = SimpleNamespace(partial=["speed_dependence+creep"], candidates=[], final=fit,
                           final_tests=rejects, base=SimpleNamespace(rmse=0.470),
                           model=SimpleNamespace(candidates=[]))
    text = _partly_text(diag)
    assert "noise level" not in text and "0.316" in text and "partly explained" in text


def test_a_fit_whose_test_accepts_says_so_with_a_p_value_that_is_not_rounded_to_zero():
    # accepted at α = 1e-3 with a combined p of 3 x 1e-3: the p printed is 3.0e-03, not
    # "0.00" (which read as a rejection)
    accepts = _tests(1e-3)
    assert not accepts.systematic
    assert verdict_status(accepts, lowers=True) == "effect_found"
    claim = noise_claim(accepts)
    assert "at the noise level" in claim and "3.0e-03" in claim
    assert p_text(0.004) == "4.0e-03" and p_text(0.25) == "0.25"


def test_no_candidate_that_lowers_the_misfit_is_unexplained():
    assert verdict_status(_tests(1e-9), lowers=False) == "unexplained"
