"""The foot-contact tuner's choice rule (training.tune_contacts.choose) on hand-made scores."""
from training.tune_contacts import choose


def row(toe_speed, pa_mpjpe, truth_speed=0.19):
    """A score tuple as tune_contacts.score returns it: toe speed, the truth's, MPJPE,
    PA-MPJPE, Acc."""
    return (toe_speed, truth_speed, 0.04, pa_mpjpe, 0.013)


def test_slowest_toes_among_the_tied_least_pa_mpjpe():
    results = [("a", row(0.18, 0.022600)),      # tied with the least, faster toes
               ("b", row(0.15, 0.022605)),      # tied (within 0.01 mm), slowest: chosen
               ("c", row(0.10, 0.022700)),      # slower still but 0.1 mm worse
               ("d", row(0.25, 0.022500))]      # least PA-MPJPE, but faster than the truth
    assert choose(results)[0] == "b"


def test_the_tie_width_decides_which_settings_compete():
    results = [("a", row(0.18, 0.022600)), ("b", row(0.15, 0.022605))]
    assert choose(results, tie=0.0)[0] == "a"
    assert choose(results, tie=1e-5)[0] == "b"


def test_no_setting_as_still_as_the_truth():
    assert choose([("a", row(0.30, 0.02)), ("b", row(0.20, 0.02))]) is None
    assert choose([]) is None
