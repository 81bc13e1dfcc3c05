"""Leave-one-out evaluation of sparse, multiplexed and combined acquisition (``btf evaluate acquisition``).

Measures every acquisition strategy of the thesis against the full ground
truth of a simulated database (``docs/evaluation.md``: scale, noise model,
strategies, claims):

1. **Truth database** (:mod:`.truth`, :func:`ensure_truth_database`): one
   ``btf-texture`` store per material, rendered straight from the virtual
   dome's renderer, one Dask task per view.
2. **Bases** (:mod:`.graph`, :func:`fit_bases`): per-material bases by
   :func:`tasks.model.fit_material` (one Dask task per material); per
   held-out material the class bases are merged *without* it
   (:func:`leave_one_out_bases`), as ``btf build-db``'s leave-one-out does.
3. **Measurements, reconstruction, scores** (:mod:`.graph`,
   :func:`evaluate_materials`): one Dask graph over (material, band) tasks,
   the numerics in :mod:`btfcore.acquisition.band_evaluation` and the
   strategies in the registry of :mod:`btfcore.acquisition.strategies`.
4. **Claims and tables** (:mod:`.claims`), **renderings and report**
   (:mod:`.report`); :mod:`.run` runs the whole evaluation
   (:func:`evaluate_acquisition`).
5. **Reuse** (:mod:`.reuse`): every finished result (a material's scores, the
   rendered materials' reconstruction stores and figures) is stored with the
   content key of its inputs; a rerun reuses it while the key is unchanged and
   says how much it reused (the summary's ``"reused"``).

:mod:`.config` holds :class:`EvaluationConfig`. Every public name of the
package's modules used by the flows and tests is importable from here.
"""

from btfcore.acquisition.band_evaluation import (
    CHROMA_MAX,
    LOG_Y_MAX,
    BandScores,
    BandTruth,
    demultiplex_views,
    finish_scores,
    floor_name,
    noise_free_band,
    noisy_multiplexed,
    noisy_rows,
    noisy_single,
    reconstruct_band,
    reconstruct_strategies,
    score_band,
)
from btfcore.acquisition.strategies import (
    REGISTRY,
    THESIS_N_S,
    THESIS_PAIRS,
    Geometry,
    Strategy,
    StrategyBases,
    build_strategies,
    floor_kinds,
    scaled_pairs,
    strategy_names,
)
from tasks.evaluate_acquisition.claims import (
    class_means,
    claims,
    floor_means,
    overall_means,
    predicted_times,
    thesis_tables,
)
from tasks.evaluate_acquisition.config import (
    STRUCTURED_CLASSES,
    TRUTH_KIND,
    EvaluationConfig,
    TruthSpec,
    truth_specs,
)
from tasks.evaluate_acquisition.graph import (
    EVAL_BASES,
    band_maxima,
    band_variance,
    bands,
    create_reconstruction_store,
    evaluate_band,
    evaluate_materials,
    fit_bases,
    leave_one_out_bases,
)
from tasks.evaluate_acquisition.report import (
    abrdf_images,
    env_map_path,
    render_one,
    renderings,
    scale_of,
    write_acquisition_report,
)
from tasks.evaluate_acquisition.reuse import RESULTS_VERSION, figures_key, reuse_message, scores_key
from tasks.evaluate_acquisition.run import evaluate_acquisition
from tasks.evaluate_acquisition.truth import (
    create_truth_store,
    ensure_truth_database,
    pending_truth_specs,
    prepare_truth_material,
    render_truth_view,
)

__all__ = [
    "CHROMA_MAX", "EVAL_BASES", "LOG_Y_MAX", "REGISTRY", "RESULTS_VERSION", "STRUCTURED_CLASSES", "THESIS_N_S",
    "THESIS_PAIRS", "TRUTH_KIND", "BandScores", "BandTruth", "EvaluationConfig", "Geometry", "Strategy",
    "StrategyBases", "TruthSpec", "abrdf_images", "band_maxima", "band_variance", "bands", "build_strategies",
    "claims", "class_means", "create_reconstruction_store", "create_truth_store", "demultiplex_views",
    "ensure_truth_database", "env_map_path", "evaluate_acquisition", "evaluate_band", "evaluate_materials",
    "figures_key", "finish_scores", "fit_bases", "floor_kinds", "floor_means", "floor_name",
    "leave_one_out_bases", "noise_free_band", "noisy_multiplexed", "noisy_rows", "noisy_single", "overall_means",
    "pending_truth_specs", "predicted_times", "prepare_truth_material", "reconstruct_band", "reconstruct_strategies",
    "render_one", "render_truth_view", "renderings", "reuse_message", "scale_of",
    "scaled_pairs", "score_band", "scores_key", "strategy_names", "thesis_tables", "truth_specs",
    "write_acquisition_report",
]
