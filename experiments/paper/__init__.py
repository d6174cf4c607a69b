"""The paper's experiments (Sec. IV): learning curves (`curves`), noise robustness (`noise_robustness`)
and transfer learning (`transfer_learning`), each a command that trains its runs one after another
through `grid` and writes its table and plots into results/."""
