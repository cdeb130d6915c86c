"""Recording files and their conventions: the Status channel, the synthetic mark, BDF
writing, channel names, the formats read (BDF/EDF/FIF/BrainVision/EEGLAB/XDF), epochs."""
