import cProfile, pstats, sys, time, io, os
import warp as wp
import vnc_warp as vw
out = os.environ.get("OUT", "/tmp")
name = sys.argv[1]
m = vw.load_mesh(f".gpudata/meshes/{name}")
# warm-up: compile every module the flow uses
vw.flow(vw.load_mesh(".gpudata/meshes/spot_lowres.obj"), stages=4, faces=3000, device="cuda:0", progress=False)
wp.synchronize()
t = time.perf_counter()
pr = cProfile.Profile(); pr.enable()
traj = vw.flow(m, stages=32, faces=50000, device="cuda:0", progress=False, out_dir=f"/tmp/traj_{name}")
wp.synchronize(); pr.disable()
wall = time.perf_counter() - t
print("wall", wall)
s = io.StringIO()
st = pstats.Stats(pr, stream=s); st.sort_stats("tottime").print_stats(45)
st.sort_stats("cumulative").print_stats(90)
open(f"{out}/prof_{name}.txt", "w").write(f"wall {wall}\n" + s.getvalue())
pr.dump_stats(f"{out}/prof_{name}.pstats")
