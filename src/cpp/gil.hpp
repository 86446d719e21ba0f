// closedchain._core: Python's global interpreter lock around the integration loops.
//
// A loop releases the lock for its arithmetic (GilRelease), so that other Python threads
// run meanwhile (closedchain.simulate_batch runs one loop per thread), and takes it back
// for every call into Python from inside the loop (GilHeld: a Python tau(t, q, v), a
// progress callback, the Ctrl-C check) and to build its result.

#pragma once

#include <Python.h>

namespace closedchain {

/// Releases the GIL from construction until restore() or destruction, whichever comes
/// first (an exception thrown by the loop takes it back on the way out).
class GilRelease {
 public:
  GilRelease() : state_(PyEval_SaveThread()) {}
  ~GilRelease() { restore(); }
  GilRelease(const GilRelease &) = delete;
  GilRelease &operator=(const GilRelease &) = delete;

  /// Take the GIL back (before the loop's result is turned into Python objects).
  void restore() {
    if (state_ == nullptr) return;
    PyEval_RestoreThread(state_);
    state_ = nullptr;
  }

 private:
  PyThreadState *state_;  ///< The thread's state while released; nullptr once restored.
};

/// Holds the GIL for its lifetime: a call into Python from a loop that released it (when
/// the thread holds it already, as outside a loop, only a counter changes).
class GilHeld {
 public:
  GilHeld() : state_(PyGILState_Ensure()) {}
  ~GilHeld() { PyGILState_Release(state_); }
  GilHeld(const GilHeld &) = delete;
  GilHeld &operator=(const GilHeld &) = delete;

 private:
  PyGILState_STATE state_;  ///< What PyGILState_Release restores.
};

}  // namespace closedchain
