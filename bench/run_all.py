"""Run every benchmark (make bench); the LAST line merges their name=value pairs.

Usage: python bench/run_all.py [--quick]
"""
import pathlib
import subprocess
import sys

HERE = pathlib.Path(__file__).resolve().parent
SCRIPTS = ["bench_core.py", "bench_method.py", "bench_train.py", "bench_ros.py", "bench_dual.py", "bench_fuzz.py",
           "bench_data.py"]


def main() -> int:
    quick = ["--quick"] if "--quick" in sys.argv[1:] else []
    pairs, failed = [], []
    for name in SCRIPTS:
        print(f"== {name} ==", flush=True)
        proc = subprocess.run([sys.executable, str(HERE / name), *quick], stdout=subprocess.PIPE, text=True)
        out = proc.stdout.rstrip().splitlines()
        print("\n".join(out), flush=True)
        if proc.returncode != 0 or not out or "=" not in out[-1]:
            failed.append(name)
            continue
        pairs.append(out[-1].strip())
    if failed:
        print(f"benchmarks failed: {failed}", file=sys.stderr)
    print(" ".join(pairs))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
