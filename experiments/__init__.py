"""Research questions about the product, each answered by one experiment: ``python -m experiments.<name>``.

- ``fidelity``: how well the supernet's estimates rank the space against long stand-alone trainings
  (``--only short_supernet``: a supernet stopped short of its recipe against a short recipe completed);
- ``search_value``: whether the search earns its time, against random sampling, random retraining and
  proxy training, and how it should choose its finalists and the envelope's networks;
- ``held_out``: a study's winner against the paper design, retrained and measured on frames the study
  never saw;
- ``resolution``: estimating at the search's small size and deploying at 224x224;
- ``scan_model``: training on the ideal centre row against a realistic LiDAR model;
- ``photometric``: whether a photometric score, where a recording has no depth, ranks paths and networks
  as RMSE would;
- ``early_paths``: self-distillation, the never-worse rule and heads sized for their position, on the
  paper design;
- ``table2``: the paper's Table 2 with the explorer's row;
- ``low_res_pass``: a whole network run first at a lower resolution, before the full-resolution one.

The shared pieces (stand-alone labels, rank figures, the strategies' machinery) are the helper package
``experiments.lib``. Experiments run on the benchmarks' harness (``benchmarks.harness``): repetitions,
interleaving, and a JSON record under ``benchmarks/results/<record>/``, which the evidence page of the
docs reads.
"""
