# Rules of the segment stage(s): see srfpipe/ for the code; rules stay thin.
