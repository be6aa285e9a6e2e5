"""Search over boxes and points: the branch-and-bound driver and its frontier, rounds in
flight, the grid and the falsifier, witnesses, the tree estimate, and where work
runs (`certify.search.distributed`)."""
