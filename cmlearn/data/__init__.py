"""Datasets from the physics: surrogate tasks, LGVI data generation, training windows."""
from .generate import (cached_dataset, data_hash, dataset_path, generate_dataset, load_dataset, reference_rollout,
                       scene_rollout, simulate_task)
from .tasks import TASKS, SurrogateTask, get_task

__all__ = ["TASKS", "SurrogateTask", "get_task", "cached_dataset", "data_hash", "dataset_path", "generate_dataset",
           "load_dataset", "reference_rollout", "scene_rollout", "simulate_task"]
