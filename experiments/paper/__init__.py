"""The paper's experiments (Sec. IV): learning curves (`curves`), noise robustness (`noise_robustness`)
and transfer learning (`transfer_learning`), each a command that trains its runs one after another
through `grid` and writes its table and plots into results/; `claims` judges the paper's claims on their runs,
and `results_docs` writes docs/results.md from each experiment's figures and runs."""
