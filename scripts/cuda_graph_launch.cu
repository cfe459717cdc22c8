// What the driver alone takes to launch a CUDA graph: cuGraphLaunch's host time for a straight line of N kernel nodes
// (1-128), by how the graph is made: instantiated with flags 0 or CUDA_GRAPH_INSTANTIATE_FLAG_USE_NODE_PRIORITY (as
// XLA's command buffers are), with or without a priority attribute on each node, with or without programmatic (PDL)
// edges between the nodes. Median of 60 launches after the stream went idle, and of 60 back to back; JSON lines.
// XLA's programs of as many kernels: graph_launch_probe.py. GPU only:
//
//     nvcc -O2 -arch=sm_90 -o /tmp/cuda_graph_launch scripts/cuda_graph_launch.cu -lcuda && /tmp/cuda_graph_launch
#include <cuda.h>
#include <cuda_runtime.h>
#include <chrono>
#include <cstdio>
#include <vector>
#include <algorithm>

__global__ void step(float* x, int n) {
  int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i < n) x[i] = x[i] * 1.0001f + 0.5f;
}

#define CK(x)                                                  \
  do {                                                         \
    CUresult r = (x);                                          \
    if (r != CUDA_SUCCESS) {                                   \
      const char* s;                                           \
      cuGetErrorString(r, &s);                                 \
      printf("%s: %s\n", #x, s);                               \
      return 1;                                                \
    }                                                          \
  } while (0)

int run(int nodes, bool node_priority_flag, bool set_priority, bool pdl_edges, CUstream stream, float* buf, int n) {
  CUgraph g; CK(cuGraphCreate(&g, 0));
  cudaFunction_t fn; cudaGetFuncBySymbol(&fn, (const void*)step);
  CUgraphNode prev = nullptr;
  for (int k = 0; k < nodes; ++k) {
    void* args[] = {&buf, &n};
    CUDA_KERNEL_NODE_PARAMS p{};
    p.func = (CUfunction)fn; p.gridDimX = (n + 255) / 256; p.gridDimY = 1; p.gridDimZ = 1;
    p.blockDimX = 256; p.blockDimY = 1; p.blockDimZ = 1; p.kernelParams = args;
    CUgraphNode node;
    if (prev && pdl_edges) {
      CUgraphEdgeData e{};
      e.from_port = CU_GRAPH_KERNEL_NODE_PORT_PROGRAMMATIC;
      e.type = CU_GRAPH_DEPENDENCY_TYPE_PROGRAMMATIC;
      CUgraphNodeParams np{}; np.type = CU_GRAPH_NODE_TYPE_KERNEL; np.kernel.func = p.func;
      np.kernel.gridDimX = p.gridDimX; np.kernel.gridDimY = 1; np.kernel.gridDimZ = 1;
      np.kernel.blockDimX = 256; np.kernel.blockDimY = 1; np.kernel.blockDimZ = 1; np.kernel.kernelParams = args;
#if CUDA_VERSION >= 13000
      CK(cuGraphAddNode(&node, g, &prev, &e, 1, &np));
#else
      CK(cuGraphAddNode_v2(&node, g, &prev, &e, 1, &np));
#endif
    } else {
      CK(cuGraphAddKernelNode(&node, g, prev ? &prev : nullptr, prev ? 1 : 0, &p));
    }
    if (set_priority) {
      CUkernelNodeAttrValue v{}; v.priority = 0;
      CK(cuGraphKernelNodeSetAttribute(node, CU_KERNEL_NODE_ATTRIBUTE_PRIORITY, &v));
    }
    prev = node;
  }
  CUgraphExec exec;
  CK(cuGraphInstantiate(&exec, g, node_priority_flag ? CUDA_GRAPH_INSTANTIATE_FLAG_USE_NODE_PRIORITY : 0));
  CK(cuGraphUpload(exec, stream));
  for (int w = 0; w < 5; ++w) CK(cuGraphLaunch(exec, stream));
  cuStreamSynchronize(stream);
  std::vector<double> idle, b2b;
  for (int it = 0; it < 60; ++it) {
    cuStreamSynchronize(stream);
    auto t0 = std::chrono::steady_clock::now();
    CK(cuGraphLaunch(exec, stream));
    auto t1 = std::chrono::steady_clock::now();
    idle.push_back(std::chrono::duration<double, std::micro>(t1 - t0).count());
  }
  for (int it = 0; it < 60; ++it) {
    auto t0 = std::chrono::steady_clock::now();
    CK(cuGraphLaunch(exec, stream));
    auto t1 = std::chrono::steady_clock::now();
    b2b.push_back(std::chrono::duration<double, std::micro>(t1 - t0).count());
  }
  cuStreamSynchronize(stream);
  std::sort(idle.begin(), idle.end()); std::sort(b2b.begin(), b2b.end());
  printf("{\"nodes\": %d, \"instantiate_node_priority\": %d, \"priority_attr\": %d, \"pdl_edges\": %d, "
         "\"launch_after_idle_us\": %.1f, \"launch_back_to_back_us\": %.1f}\n",
         nodes, node_priority_flag, set_priority, pdl_edges, idle[30], b2b[30]);
  cuGraphExecDestroy(exec); cuGraphDestroy(g);
  return 0;
}

int main() {
  cudaFree(0);
  float* buf; int n = 768 * 1152; cudaMalloc(&buf, n * sizeof(float)); cudaMemset(buf, 0, n * sizeof(float));
  CUstream s; cuStreamCreate(&s, CU_STREAM_NON_BLOCKING);
  for (int nodes : {1, 16, 64, 128})
    for (int flag = 0; flag < 2; ++flag)
      for (int attr = 0; attr < 2; ++attr)
        for (int pdl = 0; pdl < 2; ++pdl)
          if (run(nodes, flag, attr, pdl, s, buf, n)) return 1;
  return 0;
}
