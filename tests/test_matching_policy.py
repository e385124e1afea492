import pytest

from detmatch.config import ExperimentConfig, apply_overrides, apply_preset, load_config
from detmatch.matching_policy import MatchingPolicy


def test_the_policy_is_built_from_the_ssl_section():
    """tau_hung as set; the outside-view fallback at tau_3d; tau_3d_unmatched, 1.0 meaning off."""
    assert MatchingPolicy.from_config(ExperimentConfig().ssl) == MatchingPolicy(-1.5, 0.3, 0.6)
    changed = apply_overrides(
        load_config("tiny"), ["ssl.tau_hung=-2", "ssl.tau_3d=0.4", "ssl.tau_3d_unmatched=0.7"]
    )
    policy = MatchingPolicy.from_config(changed.ssl)
    assert policy == MatchingPolicy(tau_hung=-2.0, tau_3d_outside_view=0.4, tau_3d_unmatched=0.7)
    assert isinstance(policy.tau_hung, float)  # the TOML integer -2 is stored as a float
    # The paper: only matched objects in view, the fallback outside it.
    paper = MatchingPolicy.from_config(apply_preset(changed, "paper").ssl)
    assert paper == MatchingPolicy(tau_hung=-1.5, tau_3d_outside_view=0.4, tau_3d_unmatched=None)
    assert paper.with_overrides(tau_3d_outside_view=0.3) == MatchingPolicy()  # the defaults
    everything_off = apply_overrides(load_config("tiny"), ["ssl.tau_3d=1.0"])
    assert MatchingPolicy.from_config(everything_off.ssl).tau_3d_outside_view is None


def test_overrides_replace_the_values_they_name_and_are_checked():
    served = MatchingPolicy(tau_hung=-1.5, tau_3d_outside_view=0.3, tau_3d_unmatched=None)
    assert served.with_overrides() == served
    assert served.with_overrides(tau_hung=50, tau_3d_unmatched=0.1) == MatchingPolicy(
        50.0, 0.3, 0.1
    )  # a threshold the served policy has off is turned on by the request
    assert served.with_overrides(outside_view_fallback=False) == MatchingPolicy(-1.5, None, None)
    # Without the fallback the outside-view threshold is not used, so it is not checked.
    assert served.with_overrides(tau_3d_outside_view=1.5, outside_view_fallback=False) == (
        MatchingPolicy(-1.5, None, None)
    )
    refused = {
        "tau_hung": (float("nan"), "tau_hung: expected a finite number, got nan"),
        "tau_3d_outside_view": (
            1.5,
            r"tau_3d_outside_view: expected a probability threshold in \[0, 1\), got 1.5",
        ),
        "tau_3d_unmatched": (-0.1, r"tau_3d_unmatched: expected a probability threshold"),
    }
    for name, (value, message) in refused.items():
        with pytest.raises(ValueError, match=message):
            served.with_overrides(**{name: value})
    with pytest.raises(ValueError, match="tau_hung: expected a finite number, got True"):
        served.with_overrides(tau_hung=True)
    with pytest.raises(ValueError, match="tau_3d_unmatched: expected a finite number, got '0.5'"):
        MatchingPolicy(tau_3d_unmatched="0.5")
