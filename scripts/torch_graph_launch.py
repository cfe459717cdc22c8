"""What the driver takes to launch a CUDA graph captured by torch: `CUDAGraph.replay`'s host time for a graph of 1, 16,
64 and 128 small kernels (an in-place multiply on SigLIP's activation shape, f32), after the GPU went idle and back
to back, medians of 50. The same driver's launch of graphs built by hand: `cuda_graph_launch.cu`; XLA's programs of
as many kernels: `graph_launch_probe.py`. GPU only, torch with CUDA:

    python3 scripts/torch_graph_launch.py
"""

import time

import torch


def main() -> None:
    x = torch.randn(768, 1152, device="cuda")
    for n in (1, 16, 64, 128):
        graph, stream = torch.cuda.CUDAGraph(), torch.cuda.Stream()
        with torch.cuda.stream(stream):
            x.clone().mul_(1.0001)   # warm the kernel up outside the capture
            torch.cuda.synchronize()
            with torch.cuda.graph(graph):
                y = x * 1.0001
                for _ in range(n - 1):
                    y.mul_(1.0001)
        torch.cuda.synchronize()
        for mode in ("idle", "b2b"):
            times = []
            for _ in range(50):
                if mode == "idle":
                    torch.cuda.synchronize()
                start = time.perf_counter()
                graph.replay()
                times.append(time.perf_counter() - start)
            torch.cuda.synchronize()
            times.sort()
            print(f"torch graph of {n} kernels, {mode}: median launch {times[len(times) // 2] * 1e6:.1f} us")


if __name__ == "__main__":
    main()
