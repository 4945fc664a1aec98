"""Preferences from people: a label queue shared with a labelling page, and the sources training reads it through.

The page itself (``sb3-dipper-label``) lives in :mod:`sb3_dipper.labelling.app`; it needs the ``label`` extra.
:func:`start_label_page` serves it from a training process (``sb3-dipper-zoo train --label-page``).
"""

from sb3_dipper.labelling.queue import LabelQueue
from sb3_dipper.labelling.sources import (
    NoisyLabeler,
    ProgressTieBreaker,
    QueuedPreferenceSource,
    label_queue_directory,
    preference_labeler,
    preference_source_from,
)
from sb3_dipper.labelling.training_page import start_label_page

__all__ = [
    "LabelQueue",
    "NoisyLabeler",
    "ProgressTieBreaker",
    "QueuedPreferenceSource",
    "label_queue_directory",
    "preference_labeler",
    "preference_source_from",
    "start_label_page",
]
