// A capacity-1 worker for long background work that must not hold a task-scheduler thread while
// frames flow (a global bundle adjustment runs for seconds; on two cores a TBB worker blocked on
// it would stall extraction or local mapping). Start() waits for the previous task, then runs the
// new one on the worker's own thread.
// Concurrency: Start() and Wait() from one thread at a time (the owner's); the task runs on the
// worker thread. The destructor waits for the running task.
#pragma once

#include <functional>
#include <thread>

namespace flatslam {

class BackgroundWorker {
 public:
  BackgroundWorker() = default;
  BackgroundWorker(const BackgroundWorker&) = delete;
  BackgroundWorker& operator=(const BackgroundWorker&) = delete;
  ~BackgroundWorker() { Wait(); }

  void Start(std::function<void()> task) {
    Wait();
    thread_ = std::thread(std::move(task));
  }
  // Blocks until the running task (if any) has returned.
  void Wait() {
    if (thread_.joinable()) thread_.join();
  }

 private:
  std::thread thread_;
};

}  // namespace flatslam
