"""Evaluation: the LiDAR detection-ability study, the detection evaluator, reports and figures.

The paper's definitions they apply (ranges, levels, LiDAR-detected) live in detbench.data.regions.
"""
from detbench.eval.evaluate import (
    EvalFrame,
    Predictions,
    ap_r40,
    ap_r40_ranked,
    eval_frame_from_frame,
    evaluate,
    evaluate_predictions,
    parse_prediction_file,
    read_prediction_dir,
)
from detbench.eval.report import (
    combine_reports,
    combined_csv,
    combined_markdown,
    plot_by_height,
    plot_by_level,
    plot_by_range,
    report_to_csv,
    report_to_markdown,
)
from detbench.eval.ability import AbilityStudy, ability_markdown
from detbench.eval.ability_plots import plot_bev, save_ability_figures
