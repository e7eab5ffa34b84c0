"""The solitary-wave side: phi^4 kink-antikink collisions (phi4, sweep) and the seed
paper's Fig. 1 for an apparatus (compare)."""
