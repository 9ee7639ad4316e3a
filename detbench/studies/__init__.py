"""The studies built on the simulator, the evaluator and training (one layer above detbench.train).

ability, ability_plots       how many vehicles a LiDAR at each height hits (the paper's Tables IV-VI, Fig. 5-7)
ability_tables               an ability report as Markdown (ability.md)
ability_run                  the ability study fed from the simulator or a dataset (tools/analyze.py)
calibration                  the statistics that judge the simulator's ability figures against the paper's
calibration_check            the seeds simulated and judged, the report laid out (tools/check_calibration.py)
sweep, sweep_plots           one sensor at many heights: LDR and the placement scores, with intervals
sweep_sim                    the height sweep fed from the simulator (tools/sweep.py)
placement                    training-free placement scores from ray coverage and occupancy
rankcorr                     rank correlation of placement scores with trained detectors' figures
cross_height                 detectors trained at one height and tested at the others
study_summary                the answers that open a study's report (best height, best model)
seeds                        figures over several training seeds: the mean, its interval over scenes and seeds
seed_cells, seed_checks      the seed statistics' typed cells; the checks that reports can be combined
seed_markdown                study.md's sections on training seeds
student_t                    Student's t quantile (the seed statistics' t factor)
study                        the whole study from its arguments (tools/study.py)
study_plan                   the study's plan: names, heights, seeds, run folders, each stage's inputs
study_jobs                   the plan as a graph of jobs
study_results                the finished outputs read into study.json
study_report                 study.md rendered from study.json
commands                     the command lines of the studies' jobs (the tools they run)
tradeoff                     the trade study's Pareto flags, planner, cost model, report and figures
tradeoff_points              the trade study's knobs and points
tradeoff_worker              one point measured in its own process (python -m detbench.studies.tradeoff_worker)
tradeoff_sweep               the trade sweep's scheduler within a budget, resuming (tools/tradeoff.py)
executor                     the jobs and tasks run as child processes of this machine, with a deadline
cpu_load                     how many jobs this machine has room for: usable cores less the other load
jobs                         the study's job graph, its scheduler and the driver that runs it
ray_executor                 the study's jobs as tasks of a Ray cluster
registry                     what the studies need of the detector registry, which the tools pass in
"""
