"""``sb3_gccp reproduce``: the paper's Tables I and II and Figs. 5-8, every method on the same budget.

The methods of Table I (DQN, PPO and SAC-Discrete on the flat env; ours, the full hierarchy) and of
Table II (ours with the constant-velocity predictor, without GCCP, without the goal condition) train
for the same number of episodes N_e per training seed. The four hierarchy variants share one
motion-planner per seed (trained first, or given with ``--planner``); its pre-training is an extra cost
of ours, reported in ``results.json``. Every method is then evaluated on the same seeded traffic
flows per task (seeds ``eval_seed ..``), the flat env and the option env resetting the same world.

Folders::

    <log_folder>/reproduce/<preset>/
        preset.yml                      the preset settings these runs were made with
        seed<k>/planner/                the motion-planner run (none with --planner)
        seed<k>/<method>/               a decider run folder (hierarchy variants, see
                                        training.decider) or a baseline run folder (see
                                        training.baselines), plus training.json once training
                                        finished and evaluation.json
        seed<k>/predictor_errors.json   Fig. 7's numbers
        logs/seed<k>_<job>.log          each job's output, with --jobs N
        submitit/                       submitit's pickles and job logs, with --launcher submitit
    <out>/
        configs/<method>.yml            the zoo file each method trained from (and configs/planner.yml)
        records/seed<k>/<method>/       each run's training.json, evaluation.json and episodes.csv, and
                                        records/seed<k>/predictor_errors.json
        table1.md, table2.md            the paper's tables: success / collision per task, timeouts
        results.csv, results.json       one row per method x seed x task; everything behind the tables
        fig5_baselines.png              success rate vs episode, ours vs the baselines
        fig6_ablations.png              success rate vs episode, ours vs the ablations
        fig7_predictor_errors.png       ADE/FDE at 1 s: learned, no-goal and constant-velocity predictor
        fig8_predictions.png            goal-conditioned predictions in three scenes

Every (method, seed) run is a job (:mod:`~sb3_gccp.reproduce.jobs`): the hierarchy variants of a
seed after its planner job, the baselines at once. They run here one after another, N at once in
processes, or through submitit (:mod:`~sb3_gccp.reproduce.launchers`); the tables are then built from
the run folders alone (:mod:`~sb3_gccp.reproduce.collect`, also ``reproduce --collect``). Running the
command again skips every job whose run holds ``training.json`` and a matching ``evaluation.json``; an
unfinished planner, hierarchy variant or baseline continues from its last checkpoint, or starts over
without one.

Modules: :mod:`~sb3_gccp.reproduce.methods` (the rows of the tables), :mod:`~sb3_gccp.reproduce.plan`
(presets, each method's zoo entry, the checked request), :mod:`~sb3_gccp.reproduce.runner` (training
and evaluating one run once), :mod:`~sb3_gccp.reproduce.jobs` (the job graph, the job function),
:mod:`~sb3_gccp.reproduce.launchers` (where jobs run, the scheduler),
:mod:`~sb3_gccp.reproduce.collect` (the results from run folders), :mod:`~sb3_gccp.reproduce.report`
(tables and CSV) and :mod:`~sb3_gccp.reproduce.figures` (Figs. 5-8).
"""
