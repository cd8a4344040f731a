"""Chamfer AP under the two protocols of the field: ``vector`` (MapTR, default) and ``raster``
(HDMapNet / InstaGraM paper). See /work/shared/EVAL_PROTOCOLS.md and each module's docstring.

    from instagram_hdmap.evaluation import Evaluator
    ev = Evaluator("vector"); ev.update(preds, gts); metrics = ev.compute()
"""

from .consistency import ConsistentAPMeter, FlickerMeter
from .evaluator import CLASSES, PROTOCOLS, Evaluator, format_table
from .inputs import EvaluationInputError
from .io import SubmissionError, read_submission, write_submission
from .submission_ap import evaluate_files

__all__ = [
    "CLASSES",
    "PROTOCOLS",
    "EvaluationInputError",
    "Evaluator",
    "ConsistentAPMeter",
    "FlickerMeter",
    "SubmissionError",
    "evaluate_files",
    "format_table",
    "read_submission",
    "write_submission",
]
