"""Callbacks our hyperparameter files name under ``callback`` (rl-zoo3 imports them by their dotted name)."""

from __future__ import annotations

from pathlib import Path

from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import CSVOutputFormat


class CSVProgressCallback(BaseCallback):
    """Also write the logger's records to ``progress.csv`` beside the run's monitor files.

    rl-zoo3 logs to stdout (and TensorBoard); ``zoo_scripts/plot.py`` reads ``progress.csv`` for the hierarchical
    metrics (``rollout/subgoal_distance``, ``rollout/low_value``). Our YAML files name this class under ``callback``.
    The file is created exclusively: a run never appends its rows to another run's ``progress.csv``.
    """

    def _init_callback(self) -> None:
        writer = self.training_env.get_attr("results_writer", indices=[0])[0]
        if writer is None:  # a Monitor without a file: nowhere to put progress.csv
            return
        path = Path(writer.file_handler.name).parent / "progress.csv"
        try:
            path.open("x").close()
        except FileExistsError:
            raise FileExistsError(
                f"{path} already exists: another run logs to the same folder. Give each run its own monitor folder "
                "(sb3-dipper-zoo train does: it creates each run folder exclusively)."
            ) from None
        self.model.logger.output_formats.append(CSVOutputFormat(str(path)))

    def _on_step(self) -> bool:
        return True
