"""Parameter recovery study (experiments/recovery/): `python -m experiments.recovery [--quick] [--report] ...`."""
from experiments.recovery.report import *  # noqa: F401,F403
from experiments.recovery.report import main  # noqa: F401
