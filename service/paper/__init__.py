"""The paper reproduced (`make paper`, `ripplecal paper`): Fig. 8-12 of Dieterle, Greiner, Heidrich on the
emulated bench, beside the paper's numbers. experiments.py: what is measured (the plans, on the service
layer); scope.py: the emulator's oscilloscope for u_dq*, i_dq; figures.py: matplotlib; report.py:
results.json and report.html."""
