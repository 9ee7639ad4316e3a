"""The detection evaluator: what a user of tools/eval.py needs.

evaluate (matching, recall and AP@R40 by range and importance level), eval_frame (its input,
EvalFrame), prediction_files (one `<frame_id>.txt` per frame), bootstrap (the scene bootstrap
behind every interval), report (tables, CSV and figures of reports) and external (predictions in
other tools' formats). A frame's predictions are `Detections` (detbench/data/detections.py), as a
model's `predict` returns them. The paper's definitions it applies (ranges, levels,
LiDAR-detected) live in detbench.data.regions; the studies built on it live in detbench.studies.
"""
from detbench.data.detections import Detections
from detbench.eval.eval_frame import EvalFrame, eval_frame_from_frame
from detbench.eval.evaluate import ap_r40, ap_r40_ranked, evaluate, evaluate_predictions
from detbench.eval.prediction_files import parse_prediction_file, read_prediction_dir, write_predictions
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
