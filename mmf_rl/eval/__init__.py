from mmf_rl.eval.metrics import constant_velocity, displacement_errors, evaluate_forecasts

__all__ = ["constant_velocity", "displacement_errors", "evaluate_forecasts"]
