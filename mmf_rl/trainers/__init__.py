from mmf_rl.trainers.trainer import Trainer, TrainerConfig, TrainingStopped, seed_everything

__all__ = ["Trainer", "TrainerConfig", "TrainingStopped", "seed_everything"]
