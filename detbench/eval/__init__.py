"""The detection evaluator: what a user of tools/eval.py needs.

evaluate (matching, recall and AP@R40 by range and importance level), bootstrap (the scene
bootstrap behind every interval), report (tables, CSV and figures of reports) and external
(predictions in other tools' formats). The paper's definitions it applies (ranges, levels,
LiDAR-detected) live in detbench.data.regions; the studies built on it live in detbench.studies.
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
