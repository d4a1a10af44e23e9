"""The judgement of a command's settings, said: warnings on stderr, chosen settings as notes.

A finding of severity ``"warning"`` is a :class:`~plenopiv.errors.PlenopivWarning` (a
``warning:`` line, and listed under ``warnings`` with ``--json``); a setting chosen for the
user is a ``note:`` line. Both are recorded in full under the summary's ``judgement`` key and
the products' ``judgement`` attribute (:meth:`plenopiv.workflow.judgement.Judgement.record`).
"""

from __future__ import annotations

import sys
import warnings

from plenopiv.errors import PlenopivWarning

#: The products' attribute and the ``--json`` key that hold the judgement.
JUDGEMENT = "judgement"


def report(findings) -> None:
    """Say each finding: warnings as warnings, chosen settings as notes; advice is not said."""
    for f in findings:
        if f is None:
            continue
        if f.severity == "warning":
            warnings.warn(f.text, PlenopivWarning, stacklevel=2)
        elif f.severity == "chosen":
            print(f"note: {f.text}", file=sys.stderr, flush=True)


def experiment_judgement(exp, calibration, *, purpose: str = "velocimetry"):
    """``(experiment with its unset settings chosen, Judgement)``, said (:func:`report`).

    Judged on the calibration's effective camera at the reconstruction's f-number, before
    any work (:func:`plenopiv.workflow.judgement.judge_experiment`).
    """
    from plenopiv.workflow.judgement import camera_resolution, judge_experiment

    cam = camera_resolution(calibration.effective_camera, exp.reconstruction.f_number)
    exp, judged = judge_experiment(exp, cam, purpose=purpose)
    report(judged.findings)
    return exp, judged
