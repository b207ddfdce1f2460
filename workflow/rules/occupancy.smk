# Rules of the occupancy stage(s): see srfpipe/ for the code; rules stay thin.
