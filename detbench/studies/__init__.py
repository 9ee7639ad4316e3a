"""The studies built on the simulator, the evaluator and training (one layer above detbench.train).

ability, ability_plots   how many vehicles a LiDAR at each height hits (the paper's Tables IV-VI, Fig. 5-7)
calibration              the simulator's ability figures judged against the paper's
sweep, sweep_plots       one sensor at many heights: LDR and the placement scores, with intervals
placement                training-free placement scores from ray coverage and occupancy
rankcorr                 rank correlation of placement scores with trained detectors' figures
cross_height             detectors trained at one height and tested at the others
study_summary            the answers that open a study's report (best height, best model)
tradeoff                 the trade study's Pareto flags, planner, cost model, report and figures
"""
