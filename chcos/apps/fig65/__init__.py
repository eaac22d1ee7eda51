"""fig65 - the example system of thesis figure 6.5 (section 6.1.5), as chcos tasks.

Sensors S1, S2, S3 and a test file feed level 1 (A1, A2, the file sampler A3, the terminal/log
driver A4); B1 and B2 at level 2 command the A tasks; C1 at level 3 commands B1, B2 and A4. Each
task condenses five inputs into one output upward, the load assumption of section 6.4. The install
script ``install.chcos`` beside this file is the thesis' shell script of section 6.3.
"""


from chcos import resources

HERE = resources.path("chcos.apps.fig65")
SCRIPT = HERE / "install.chcos"
