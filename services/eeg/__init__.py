"""Stage 1: EEG ingest, preprocessing, the ErrP decoders and the virtual subject, in rooms.

From the bottom up (each room imports only the rooms below it; pyproject's import contract
keeps it so): ``signal`` (causal filters and the online preprocessing), ``recordings``
(their conventions, reading, validating and writing files, labelled epochs), ``decoding``
(the decoders, calibration and its report) and ``live`` (ingest, LSL, live recordings),
then ``service`` (the EEG service) and ``virtual`` (the virtual subject and its drivers).
"""
