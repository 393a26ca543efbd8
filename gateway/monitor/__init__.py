"""Live monitoring: running residual / friction / efficiency trackers, alert rules with
hysteresis, the zenoh service behind ``bsc monitor`` and its terminal dashboard.

Pure parts (:mod:`.rules`, :mod:`.trackers`, :mod:`.core`, :mod:`.dashboard`) import no zenoh;
:mod:`.service` is given an open session. Metrics and thresholds: docs/monitoring.md.
"""
from .core import Monitor
from .rules import DEFAULT_RULES, Rule, RuleEngine, RulesError, RuleSet, load_rules

__all__ = ["DEFAULT_RULES", "Monitor", "Rule", "RuleEngine", "RuleSet", "RulesError", "load_rules"]
