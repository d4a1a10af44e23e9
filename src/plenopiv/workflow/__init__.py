"""The one place that composes the stages.

One volume, one pair, the processor a batch worker keeps, the response measurement, tracking
of a pair, planning, the experiment and the demo case.

Stages never import this package; :mod:`plenopiv.batch` and :mod:`plenopiv.cli` run over it.
"""
