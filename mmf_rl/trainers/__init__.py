from mmf_rl.trainers.checkpoint import (
    Checkpoint,
    CheckpointError,
    list_checkpoints,
    load_checkpoint,
    load_model_state,
    save_checkpoint,
)

__all__ = ["Checkpoint", "CheckpointError", "list_checkpoints", "load_checkpoint", "load_model_state",
           "save_checkpoint"]
