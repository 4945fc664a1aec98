"""Preferences from people: a label queue shared with a labelling page, and the sources training reads it through.

The page itself (``sb3-dipper-label``) lives in :mod:`sb3_dipper.labelling.app`; it needs the ``label`` extra.
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

__all__ = [
    "LabelQueue",
    "NoisyLabeler",
    "ProgressTieBreaker",
    "QueuedPreferenceSource",
    "label_queue_directory",
    "preference_labeler",
    "preference_source_from",
]
