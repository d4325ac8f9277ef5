# small_gicp (PyPI 1.0.1) on gicp_pair: median (min) ms over N runs, error vs the reference.
# Run: pip install small_gicp==1.0.1 && python3 scripts/compare_small_gicp.py 30
# Compare with: ./target/release/emr-eval gicp --runs 30 (from /work/main)
import numpy as np, small_gicp, time, sys
d='/work/shared/data/gicp_pair/'
def readply(p):
    raw=open(p,'rb').read(); h=raw.index(b'end_header\n')+len(b'end_header\n')
    n=int([l for l in raw[:h].decode().split('\n') if l.startswith('element vertex')][0].split()[-1])
    return np.frombuffer(raw[h:h+n*16],dtype='<f4').reshape(n,4)[:,:3].astype(np.float64)
S=readply(d+'source.ply'); T=readply(d+'target.ply'); ref=np.loadtxt(d+'T_target_source.txt')
def err(M):
    D=np.linalg.inv(ref)@M; return np.linalg.norm(D[:3,3])*100, np.degrees(np.arccos(np.clip((np.trace(D[:3,:3])-1)/2,-1,1)))
def timed(f, n):
    ts=[]; r=None
    for _ in range(n):
        t0=time.perf_counter(); r=f(); ts.append((time.perf_counter()-t0)*1e3)
    return r, f"{np.median(ts):6.2f} ({min(ts):6.2f})"
N=int(sys.argv[1]) if len(sys.argv)>1 else 30
for th in [1,2]:
  for typ in ['GICP','VGICP']:
    r,t=timed(lambda: small_gicp.align(T,S,registration_type=typ,downsampling_resolution=0.25,num_threads=th),N)
    e=err(r.T_target_source)
    print(f"{typ:5s} threads={th} align(raw points)            {t} ms  err {e[0]:.2f} cm {e[1]:.3f} deg  iter {r.iterations} inliers {r.num_inliers}")
    def pipe():
        tp,tt=small_gicp.preprocess_points(T,0.25,num_neighbors=20,num_threads=th)
        sp,_=small_gicp.preprocess_points(S,0.25,num_neighbors=20,num_threads=th)
        if typ=='VGICP':
            m=small_gicp.GaussianVoxelMap(1.0); m.insert(tp); return small_gicp.align(m,sp,num_threads=th)
        return small_gicp.align(tp,sp,tt,registration_type='GICP',num_threads=th)
    r,t=timed(pipe,N); e=err(r.T_target_source)
    print(f"{typ:5s} threads={th} preprocess(k=20)+align       {t} ms  err {e[0]:.2f} cm {e[1]:.3f} deg  iter {r.iterations} inliers {r.num_inliers}")
    tp,tt=small_gicp.preprocess_points(T,0.25,num_neighbors=20,num_threads=th)
    sp,_=small_gicp.preprocess_points(S,0.25,num_neighbors=20,num_threads=th)
    m=small_gicp.GaussianVoxelMap(1.0); m.insert(tp)
    f=(lambda: small_gicp.align(m,sp,num_threads=th)) if typ=='VGICP' else (lambda: small_gicp.align(tp,sp,tt,registration_type='GICP',num_threads=th))
    r,t=timed(f,N); e=err(r.T_target_source)
    print(f"{typ:5s} threads={th} align(prepared, k=20) only   {t} ms  err {e[0]:.2f} cm {e[1]:.3f} deg  iter {r.iterations} inliers {r.num_inliers}  ({sp.size()}/{tp.size()} pts)")
