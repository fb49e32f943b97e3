"""`pa refine`: the refine pipeline and the stages of its loop (odometry, deskew, registration, rounds)."""
