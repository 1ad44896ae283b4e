"""The pipeline: FreeReg on one pair and on many (layer 5, imports every method layer below it).

* :mod:`.steps`: ``depth_view`` -> ``compute_features`` -> ``match`` -> ``solve`` ->
  ``evaluate``, and ``run_pair`` / ``run_pairs`` / ``summarize`` (its names are also this
  package's: ``pipeline.run_pair``);
* :mod:`.register`: a user's own image and cloud, with or without the depth sensor's pose
  (virtual depth cameras), and the verdict on the pose found (reading the user's files is
  :mod:`freereg_lib.commands.user_inputs`).

Nothing here imports the commands, the notebooks' report helpers, training or teaching.
"""
from freereg_lib.features.matching import Matches
from freereg_lib.pipeline.steps import (
                                        DEFAULT_VARIANTS,
                                        METHODS,
                                        ROW_COLUMNS,
                                        DepthView,
                                        PairFeatures,
                                        compute_features,
                                        compute_features_batch,
                                        correct_matches,
                                        depth_view,
                                        descriptors,
                                        diffusion_maps,
                                        diffusion_maps_batch,
                                        diffusion_maps_over_t_hats,
                                        evaluate,
                                        evaluation_truth,
                                        match,
                                        rows_frame,
                                        run_pair,
                                        run_pairs,
                                        scene_hints,
                                        solve,
                                        summarize,
                                        variant_rows,
)

__all__ = ["DEFAULT_VARIANTS", "METHODS", "ROW_COLUMNS", "DepthView", "Matches", "PairFeatures", "compute_features",
           "compute_features_batch", "correct_matches", "depth_view", "descriptors", "diffusion_maps",
           "diffusion_maps_batch", "diffusion_maps_over_t_hats", "evaluate", "evaluation_truth", "match", "rows_frame", "run_pair", "run_pairs",
           "scene_hints", "solve", "summarize", "variant_rows"]
