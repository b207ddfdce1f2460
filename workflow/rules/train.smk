# Rules of the train stage(s): see srfpipe/ for the code; rules stay thin.
