from sb3_dipper.piper.piper import PIPER, LearnedRewardReplayBuffer, RewardModelSAC
from sb3_dipper.piper.policies import MlpPolicy, MultiInputPolicy, RewardModel

__all__ = ["PIPER", "LearnedRewardReplayBuffer", "MlpPolicy", "MultiInputPolicy", "RewardModel", "RewardModelSAC"]
