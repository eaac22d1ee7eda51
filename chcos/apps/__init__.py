"""apps - the applications that run on chcos, apart from the OS: the arc-welding cell of
appendix 2 (the main job), the figure 6.5 example, the benchmarks, the NBS baseline and the
generic simulated slaves. They import the OS; the OS never imports them.
"""
