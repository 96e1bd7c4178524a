"""numpy-only data layer: readers, windowing, protocols, batching. Never imports jax."""

from gst_jax.data import trajnet  # a page of its own in the API reference
from gst_jax.data.batch import SceneBatch, node_mask_from_positions
from gst_jax.data.batching import (
                                   BUCKETS,
                                   SHARED_MICRO_BATCH_MAX,
                                   TRAINING_BUCKETS,
                                   PackedStep,
                                   bucket_size,
                                   evaluation_batches,
                                   make_batch,
                                   pack_step,
                                   pad_windows,
                                   training_batches,
)
from gst_jax.data.protocols import (
                                   data_files,
                                   data_name,
                                   default_data_dir,
                                   has_validation,
                                   load_split,
                                   no_windows_message,
                                   split_frames,
)
from gst_jax.data.readers import Tracks, read_tracks
from gst_jax.data.windows import Window, WindowSet

__all__ = [
    "BUCKETS", "PackedStep", "SHARED_MICRO_BATCH_MAX", "SceneBatch",
    "TRAINING_BUCKETS", "Tracks", "Window", "WindowSet", "bucket_size", "data_files",
    "data_name", "default_data_dir", "evaluation_batches", "has_validation", "load_split",
    "make_batch", "no_windows_message", "node_mask_from_positions", "pack_step", "pad_windows",
    "read_tracks", "split_frames", "training_batches",
    # The modules, pages of their own in the API reference.
    "readers", "windows", "protocols", "trajnet",
]
