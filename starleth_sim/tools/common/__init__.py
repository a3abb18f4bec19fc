"""What several tools use: the bag reader, the console-script wrapper, the task pool, the
headless gait run and its fall rule, and the node processes (child processes, discovery kept
on this host) of the demo, the benchmarks and the tests."""
