# Finds Eigen 3.3+ (header-only) and says where it came from.
#
# pip builds get Eigen from the cmeel-eigen wheel, a build requirement in pyproject.toml: its headers
# and CMake config sit under <site-packages>/cmeel.prefix, which `python -m cmeel cmake` lists (the
# CMAKE_PREFIX_PATH entries of every cmeel package importable by that Python). So `pip install .`
# needs no system package, and every wheel is built against the one pinned Eigen.
#
# ENVI_EIGEN_FROM picks the source:
#   auto   (default) cmeel-eigen when the build's Python has it, else a system Eigen (libeigen3-dev)
#   cmeel  only cmeel-eigen; an error when it is missing (the wheel test uses this)
#   system only the usual CMake search (system packages, CMAKE_PREFIX_PATH)
# The configure log says which one was used: "envi: Eigen <version> from <source> (<include dir>)".
set(ENVI_EIGEN_FROM "auto" CACHE STRING "Where Eigen comes from: auto, cmeel or system")
set_property(CACHE ENVI_EIGEN_FROM PROPERTY STRINGS auto cmeel system)
if(NOT ENVI_EIGEN_FROM MATCHES "^(auto|cmeel|system)$")
  message(FATAL_ERROR "ENVI_EIGEN_FROM is '${ENVI_EIGEN_FROM}'; it must be auto, cmeel or system")
endif()

set(_envi_cmeel_prefixes "")
if(NOT ENVI_EIGEN_FROM STREQUAL "system" AND Python_EXECUTABLE)
  execute_process(COMMAND "${Python_EXECUTABLE}" -m cmeel cmake
                  OUTPUT_VARIABLE _envi_cmeel_out RESULT_VARIABLE _envi_cmeel_rc
                  OUTPUT_STRIP_TRAILING_WHITESPACE ERROR_QUIET)
  if(_envi_cmeel_rc EQUAL 0 AND _envi_cmeel_out)
    if(NOT WIN32)  # os.pathsep: ':' here, already ';' (a CMake list) on Windows
      string(REPLACE ":" ";" _envi_cmeel_out "${_envi_cmeel_out}")
    endif()
    set(_envi_cmeel_prefixes ${_envi_cmeel_out})
  endif()
endif()

set(ENVI_EIGEN_ORIGIN "")
if(_envi_cmeel_prefixes)
  # A cached Eigen3_DIR from an earlier configure (a system one, or a deleted pip build
  # environment) would be taken as is: search the cmeel prefixes afresh.
  if(Eigen3_DIR AND NOT Eigen3_DIR MATCHES "cmeel\\.prefix")
    unset(Eigen3_DIR CACHE)
  endif()
  find_package(Eigen3 3.3 QUIET NO_MODULE PATHS ${_envi_cmeel_prefixes} NO_DEFAULT_PATH)
  if(Eigen3_FOUND)
    set(ENVI_EIGEN_ORIGIN "cmeel")
  endif()
endif()
if(NOT ENVI_EIGEN_ORIGIN)
  if(ENVI_EIGEN_FROM STREQUAL "cmeel")
    message(FATAL_ERROR "ENVI_EIGEN_FROM=cmeel but the Python '${Python_EXECUTABLE}' has no cmeel-eigen: "
                        "pip install cmeel-eigen into it (pip builds get it from pyproject.toml)")
  endif()
  if(Eigen3_DIR MATCHES "cmeel\\.prefix")  # cached by an earlier cmeel configure
    unset(Eigen3_DIR CACHE)
  endif()
  find_package(Eigen3 3.3 QUIET NO_MODULE)
  if(NOT Eigen3_FOUND)
    message(FATAL_ERROR "Eigen 3.3+ not found. 'pip install .' gets it from the cmeel-eigen wheel; a plain CMake "
                        "build needs cmeel-eigen in the Python given by -DPython_EXECUTABLE, or the system "
                        "package (Debian/Ubuntu: libeigen3-dev)")
  endif()
  set(ENVI_EIGEN_ORIGIN "system")
endif()
get_target_property(_envi_eigen_inc Eigen3::Eigen INTERFACE_INCLUDE_DIRECTORIES)
message(STATUS "envi: Eigen ${Eigen3_VERSION} from ${ENVI_EIGEN_ORIGIN} (${_envi_eigen_inc})")
