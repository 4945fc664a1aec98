"""The labelling page served from a training process (``sb3-dipper-zoo train --label-page``).

The page itself is :mod:`sb3_dipper.labelling.app` (the ``label`` extra); it is imported only when a page is started,
so training without ``--label-page`` does not need Flask.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from sb3_dipper.labelling.sources import label_queue_directory

if TYPE_CHECKING:
    from stable_baselines3.common.base_class import BaseAlgorithm


def start_label_page(model: BaseAlgorithm, host: str, port: int) -> Any:
    """``--label-page``: serve the labelling page of ``model``'s label queue from this process while it trains.

    :param model: the model about to train; its ``preference_source`` sends pairs to people (``people:DIR`` or
        ``mixed:DIR:FRACTION``)
    :param host: the address to serve on
    :param port: the port to serve on (0: a free one)
    :return: the running server (``shutdown()`` stops it)
    """
    directory = label_queue_directory(getattr(model, "preference_source", None))
    if directory is None:
        raise ValueError(
            f"--label-page: {type(model).__name__}'s preference_source sends no pairs to people, so there is nothing "
            "to label. Train with -params \"preference_source:'people:DIR'\" (or 'mixed:DIR:FRACTION'), or leave "
            "out --label-page."
        )
    try:
        from sb3_dipper.labelling.app import serve_in_background
    except ImportError as error:
        raise ImportError(f"--label-page needs the labelling page's packages: pip install -e '.[label]' ({error})") from error
    server = serve_in_background(directory, host, port)
    # The only way to tell the person at the terminal where the page is (rl-zoo3 prints its own progress too).
    print(f"Labelling page of {directory}: http://{host}:{server.server_port}", flush=True)
    return server
