"""Profile steps and their kinds: one registered object per kind (station/steps/base.py says what
a kind is; station/steps/builtin.py holds segment, static, none, program and heat, registered on
import)."""

from station.steps import builtin
from station.steps.base import Estimates, Step, StepKind, heats, kind_names, kind_of, register, row_kinds, unregister

__all__ = ["Estimates", "Step", "StepKind", "builtin", "heats", "kind_names", "kind_of", "register", "row_kinds",
           "unregister"]
