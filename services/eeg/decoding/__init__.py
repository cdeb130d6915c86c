"""ErrP decoders and their calibration: EEGNet, window-mean LDA, xDAWN + Riemannian geometry,
the trained classifier, metrics, the calibrated posterior, the report and the files written."""
