import subprocess
import sys

HEAVY = ("lightning", "torchrl", "gymnasium", "pybullet", "cv2", "cmlearn", "matplotlib")


def test_import_physics_stays_light():
    code = "import sys, physics; print(' '.join(m for m in %r if m in sys.modules))" % (HEAVY,)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"import physics pulled in: {out.stdout.strip()}"
