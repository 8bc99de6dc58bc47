"""jaxafm's record diagnosis on records of the independent generator (tests/independent.py).

Short records (3 s at 200 Hz, the same drive code as experiments/independent_check.py) and
three candidates keep each case to seconds; the full check is the experiment.
"""

from independent import make_case, make_drive

from jaxafm.diagnose import record as D
from jaxafm.instrument.records import Record

DRIVE = make_drive(3.0, 200.0)
CANDIDATES = ("creep", "drift", "rate_dependence")


def diagnose(effect, level, seed, truth, nominal):
    c = make_case(effect, level, seed, truth, drive=DRIVE)
    record = Record(t=c["t"], u=c["u"], d=c["d"], meta={"source": f"independent generator: {effect}"})
    return D.diagnose_record(record, D.Nominal(kind=nominal), CANDIDATES, log=lambda s: None)


def test_middle_creep_is_named():
    res = diagnose("creep", "middle", 2010, "pi", "pi")
    assert res.verdict == "creep"


def test_control_same_class_blames_nothing():
    res = diagnose(None, "control", 10_000, "pi", "pi")
    assert res.verdict is None


def test_control_preisach_truth_pi_nominal_blames_nothing():
    res = diagnose(None, "control", 10_001, "preisach", "pi")
    assert res.verdict is None
