from sb3_dipper.dpo_flat.dpo_flat import DPOFlat, sample_segment_pairs
from sb3_dipper.dpo_flat.policies import MlpPolicy, MultiInputPolicy

__all__ = ["DPOFlat", "MlpPolicy", "MultiInputPolicy", "sample_segment_pairs"]
