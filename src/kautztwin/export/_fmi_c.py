"""C source and ``modelDescription.xml`` of an FMI 2.0 co-simulation FMU of a discrete LTI model.

The generated unit steps the exact zero-order-hold recursion of :mod:`kautztwin.export.fmu`

.. math::

    x_{k+1} = \\Phi x_k + \\Gamma_a\\,u_{k-d-1} + \\Gamma_b\\,u_{k-d},\\qquad
    y_k = y_\\mathrm{off} + C x_k + D\\,u^\\tau_k ,

with the input measured from ``u_offset``, a delay line of ``d + 1`` past inputs and
:math:`u^\\tau_k` the delayed input at :math:`t_k`.  The FMI 2.0 types and prototypes
are declared here from the standard's function signatures (no header files needed);
every function the standard lists for co-simulation is exported.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from datetime import UTC, datetime
from xml.sax.saxutils import quoteattr

import numpy as np
from numpy.typing import NDArray

__all__ = ["DiscreteRealisation", "c_source", "model_description", "new_guid"]

#: value references of the variables (the same in the XML and the C code)
VR_U, VR_Y, VR_U_OFFSET, VR_Y_OFFSET = 0, 1, 2, 3


@dataclass(frozen=True)
class DiscreteRealisation:
    """The recursion an FMU steps: matrices at the step ``h`` and the delay split.

    Attributes
    ----------
    Phi : ndarray of shape (n, n)
    Gamma_a, Gamma_b : ndarray of shape (n,)
        Input vectors of ``u[k-d-1]`` and ``u[k-d]``.
    C : ndarray of shape (n,)
    D : float
    h : float
        The step in seconds.
    delay_steps : int
        ``d``, whole steps of the delay.
    fractional : bool
        Whether the delay has a fractional part (then the output reads ``u[k-d-1]``).
    """

    Phi: NDArray[np.float64]
    Gamma_a: NDArray[np.float64]
    Gamma_b: NDArray[np.float64]
    C: NDArray[np.float64]
    D: float
    h: float
    delay_steps: int
    fractional: bool

    @property
    def n_states(self) -> int:
        """State dimension ``n``."""
        return int(self.Phi.shape[0])


def _num(x: float) -> str:
    """A double written so that C reads back the same value (17 significant digits)."""
    return f"{float(x):.17g}"


def _array(name: str, values: NDArray) -> str:
    flat = np.asarray(values, dtype=float).ravel()
    body = ", ".join(_num(v) for v in flat) if flat.size else "0.0"
    return f"static const double {name}[{max(flat.size, 1)}] = {{{body}}};"


_HEADER = r"""
/* ---- FMI 2.0 types and prototypes (from the standard's function signatures) ---- */
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

#if defined(_WIN32)
#define FMI2_Export __declspec(dllexport)
#else
#define FMI2_Export __attribute__((visibility("default")))
#endif

typedef void *fmi2Component;
typedef void *fmi2ComponentEnvironment;
typedef void *fmi2FMUstate;
typedef unsigned int fmi2ValueReference;
typedef double fmi2Real;
typedef int fmi2Integer;
typedef int fmi2Boolean;
typedef char fmi2Char;
typedef const fmi2Char *fmi2String;
typedef char fmi2Byte;
#define fmi2True 1
#define fmi2False 0

typedef enum { fmi2OK, fmi2Warning, fmi2Discard, fmi2Error, fmi2Fatal, fmi2Pending } fmi2Status;
typedef enum { fmi2ModelExchange, fmi2CoSimulation } fmi2Type;
typedef enum { fmi2DoStepStatus, fmi2PendingStatus, fmi2LastSuccessfulTime,
               fmi2Terminated } fmi2StatusKind;

typedef void (*fmi2CallbackLogger)(fmi2ComponentEnvironment, fmi2String, fmi2Status,
                                   fmi2String, fmi2String, ...);
typedef void *(*fmi2CallbackAllocateMemory)(size_t, size_t);
typedef void (*fmi2CallbackFreeMemory)(void *);
typedef void (*fmi2StepFinished)(fmi2ComponentEnvironment, fmi2Status);

typedef struct {
    const fmi2CallbackLogger logger;
    const fmi2CallbackAllocateMemory allocateMemory;
    const fmi2CallbackFreeMemory freeMemory;
    const fmi2StepFinished stepFinished;
    const fmi2ComponentEnvironment componentEnvironment;
} fmi2CallbackFunctions;
"""

_BODY = r"""
/* ---- the model instance ---- */
typedef struct {
    double x[NX];
    double hist[NHIST];      /* hist[j] = u[k-1-j] - u_offset, the inputs of past steps */
    double u;                /* the input, held over the current step */
    double u_offset, y_offset;
    double time;
    int log;
    char *name;
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
} Instance;

static void say(Instance *m, fmi2Status status, const char *message) {
    if (m && m->logger) {
        m->logger(m->env, m->name ? m->name : "", status, status == fmi2OK ? "log" : "error",
                  "%s", message);
    }
}

static void reset_state(Instance *m) {
    int i;
    for (i = 0; i < NX; i++) m->x[i] = 0.0;
    for (i = 0; i < NHIST; i++) m->hist[i] = 0.0;  /* at rest: u = u_offset before start */
    m->u = U_START;
    m->u_offset = U_OFFSET_START;
    m->y_offset = Y_OFFSET_START;
    m->time = 0.0;
}

/* the input u[k-j] (j >= 0) measured from u_offset, with u[k] the held input */
static double past_input(const Instance *m, int j) {
    return j == 0 ? m->u - m->u_offset : m->hist[j - 1];
}

static double output(const Instance *m) {
    double y = m->y_offset;
    int i;
    for (i = 0; i < NX; i++) y += C[i] * m->x[i];
    if (D != 0.0) y += D * past_input(m, FRACTIONAL ? DELAY_STEPS + 1 : DELAY_STEPS);
    return y;
}

static void one_step(Instance *m) {
    double xn[NX];
    double ua = past_input(m, DELAY_STEPS + 1), ub = past_input(m, DELAY_STEPS);
    int i, j;
    for (i = 0; i < NX; i++) {
        double s = GAMMA_A[i] * ua + GAMMA_B[i] * ub;
        for (j = 0; j < NX; j++) s += PHI[i * NX + j] * m->x[j];
        xn[i] = s;
    }
    for (i = 0; i < NX; i++) m->x[i] = xn[i];
    for (i = NHIST - 1; i > 0; i--) m->hist[i] = m->hist[i - 1];
    m->hist[0] = m->u - m->u_offset;
}

/* ---- common functions ---- */
FMI2_Export const char *fmi2GetTypesPlatform(void) { return "default"; }
FMI2_Export const char *fmi2GetVersion(void) { return "2.0"; }

FMI2_Export fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn,
                                           size_t nCategories, const fmi2String categories[]) {
    (void)nCategories; (void)categories;
    if (!c) return fmi2Error;
    ((Instance *)c)->log = loggingOn;
    return fmi2OK;
}

FMI2_Export fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType,
                                          fmi2String fmuGUID, fmi2String fmuResourceLocation,
                                          const fmi2CallbackFunctions *functions,
                                          fmi2Boolean visible, fmi2Boolean loggingOn) {
    Instance *m;
    (void)fmuResourceLocation; (void)visible;
    if (fmuType != fmi2CoSimulation) {
        if (functions && functions->logger)
            functions->logger(functions->componentEnvironment, instanceName, fmi2Error, "error",
                              "this FMU supports co-simulation only");
        return NULL;
    }
    if (!fmuGUID || strcmp(fmuGUID, GUID) != 0) {
        if (functions && functions->logger)
            functions->logger(functions->componentEnvironment, instanceName, fmi2Error, "error",
                              "wrong GUID %s; expected %s", fmuGUID ? fmuGUID : "(null)", GUID);
        return NULL;
    }
    m = (Instance *)calloc(1, sizeof(Instance));
    if (!m) return NULL;
    if (instanceName) {
        m->name = (char *)malloc(strlen(instanceName) + 1);
        if (m->name) strcpy(m->name, instanceName);
    }
    m->logger = functions ? functions->logger : NULL;
    m->env = functions ? functions->componentEnvironment : NULL;
    m->log = loggingOn;
    reset_state(m);
    return m;
}

FMI2_Export void fmi2FreeInstance(fmi2Component c) {
    Instance *m = (Instance *)c;
    if (!m) return;
    free(m->name);
    free(m);
}

FMI2_Export fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined,
                                           fmi2Real tolerance, fmi2Real startTime,
                                           fmi2Boolean stopTimeDefined, fmi2Real stopTime) {
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    if (!c) return fmi2Error;
    ((Instance *)c)->time = startTime;
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    return c ? fmi2OK : fmi2Error;
}

FMI2_Export fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    return c ? fmi2OK : fmi2Error;
}

FMI2_Export fmi2Status fmi2Terminate(fmi2Component c) { return c ? fmi2OK : fmi2Error; }

FMI2_Export fmi2Status fmi2Reset(fmi2Component c) {
    if (!c) return fmi2Error;
    reset_state((Instance *)c);
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                   fmi2Real value[]) {
    Instance *m = (Instance *)c;
    size_t i;
    if (!m) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        switch (vr[i]) {
            case VR_U: value[i] = m->u; break;
            case VR_Y: value[i] = output(m); break;
            case VR_U_OFFSET: value[i] = m->u_offset; break;
            case VR_Y_OFFSET: value[i] = m->y_offset; break;
            default: say(m, fmi2Error, "fmi2GetReal: unknown value reference"); return fmi2Error;
        }
    }
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                   const fmi2Real value[]) {
    Instance *m = (Instance *)c;
    size_t i;
    if (!m) return fmi2Error;
    for (i = 0; i < nvr; i++) {
        switch (vr[i]) {
            case VR_U: m->u = value[i]; break;
            case VR_U_OFFSET: m->u_offset = value[i]; break;
            case VR_Y_OFFSET: m->y_offset = value[i]; break;
            default:
                say(m, fmi2Error, "fmi2SetReal: the value reference is not an input or parameter");
                return fmi2Error;
        }
    }
    return fmi2OK;
}

#define NO_VARIABLES_OF_TYPE(fn, T)                                                     \
    FMI2_Export fmi2Status fn(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, \
                              T value[]) {                                             \
        (void)vr; (void)value;                                                         \
        if (!c) return fmi2Error;                                                      \
        if (nvr) { say((Instance *)c, fmi2Error, #fn ": the FMU has no such variable"); \
                   return fmi2Error; }                                                 \
        return fmi2OK;                                                                 \
    }
NO_VARIABLES_OF_TYPE(fmi2GetInteger, fmi2Integer)
NO_VARIABLES_OF_TYPE(fmi2GetBoolean, fmi2Boolean)
NO_VARIABLES_OF_TYPE(fmi2GetString, fmi2String)
NO_VARIABLES_OF_TYPE(fmi2SetInteger, const fmi2Integer)
NO_VARIABLES_OF_TYPE(fmi2SetBoolean, const fmi2Boolean)
NO_VARIABLES_OF_TYPE(fmi2SetString, const fmi2String)

FMI2_Export fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) {
    (void)s; say((Instance *)c, fmi2Error, "FMU states are not supported"); return fmi2Error;
}
FMI2_Export fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) {
    (void)s; say((Instance *)c, fmi2Error, "FMU states are not supported"); return fmi2Error;
}
FMI2_Export fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) {
    (void)s; say((Instance *)c, fmi2Error, "FMU states are not supported"); return fmi2Error;
}
FMI2_Export fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) {
    (void)s; (void)n; say((Instance *)c, fmi2Error, "FMU states are not supported");
    return fmi2Error;
}
FMI2_Export fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[],
                                             size_t n) {
    (void)s; (void)b; (void)n; say((Instance *)c, fmi2Error, "FMU states are not supported");
    return fmi2Error;
}
FMI2_Export fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n,
                                               fmi2FMUstate *s) {
    (void)b; (void)n; (void)s; say((Instance *)c, fmi2Error, "FMU states are not supported");
    return fmi2Error;
}
FMI2_Export fmi2Status fmi2GetDirectionalDerivative(
    fmi2Component c, const fmi2ValueReference vU[], size_t nU, const fmi2ValueReference vK[],
    size_t nK, const fmi2Real dv[], fmi2Real dz[]) {
    (void)vU; (void)nU; (void)vK; (void)nK; (void)dv; (void)dz;
    say((Instance *)c, fmi2Error, "directional derivatives are not supported");
    return fmi2Error;
}

/* ---- co-simulation ---- */
FMI2_Export fmi2Status fmi2SetRealInputDerivatives(fmi2Component c,
                                                   const fmi2ValueReference vr[], size_t nvr,
                                                   const fmi2Integer order[],
                                                   const fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    say((Instance *)c, fmi2Error, "input derivatives are not supported (inputs are held)");
    return fmi2Error;
}
FMI2_Export fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c,
                                                    const fmi2ValueReference vr[], size_t nvr,
                                                    const fmi2Integer order[], fmi2Real value[]) {
    (void)vr; (void)nvr; (void)order; (void)value;
    say((Instance *)c, fmi2Error, "output derivatives are not supported");
    return fmi2Error;
}

FMI2_Export fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                                  fmi2Real communicationStepSize,
                                  fmi2Boolean noSetFMUStatePriorToCurrentPoint) {
    Instance *m = (Instance *)c;
    double ratio;
    long n, k;
    (void)noSetFMUStatePriorToCurrentPoint;
    if (!m) return fmi2Error;
    ratio = communicationStepSize / STEP;
    n = lround(ratio);
    if (n < 1 || fabs(ratio - (double)n) > 1e-9 * (ratio > 1.0 ? ratio : 1.0)) {
        char text[200];
        snprintf(text, sizeof text,
                 "fmi2DoStep: the step %.17g s is not a positive whole multiple of the "
                 "FMU's step %.17g s", communicationStepSize, STEP);
        say(m, fmi2Error, text);
        return fmi2Error;
    }
    for (k = 0; k < n; k++) one_step(m);
    m->time = currentCommunicationPoint + communicationStepSize;
    return fmi2OK;
}

FMI2_Export fmi2Status fmi2CancelStep(fmi2Component c) { return c ? fmi2OK : fmi2Error; }

FMI2_Export fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s,
                                     fmi2Status *value) {
    (void)s;
    if (!c) return fmi2Error;
    *value = fmi2OK;
    return fmi2OK;
}
FMI2_Export fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s,
                                         fmi2Real *value) {
    if (!c) return fmi2Error;
    if (s != fmi2LastSuccessfulTime) return fmi2Discard;
    *value = ((Instance *)c)->time;
    return fmi2OK;
}
FMI2_Export fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s,
                                            fmi2Integer *value) {
    (void)s; (void)value; return c ? fmi2Discard : fmi2Error;
}
FMI2_Export fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s,
                                            fmi2Boolean *value) {
    if (!c) return fmi2Error;
    if (s != fmi2Terminated) return fmi2Discard;
    *value = fmi2False;
    return fmi2OK;
}
FMI2_Export fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s,
                                           fmi2String *value) {
    (void)s; (void)value; return c ? fmi2Discard : fmi2Error;
}
"""


def c_source(
    r: DiscreteRealisation, guid: str, *, description: str, u_start: float = 0.0
) -> str:
    """The complete C source of the FMU's shared library.

    Parameters
    ----------
    r : DiscreteRealisation
        The recursion to step.
    guid : str
        The FMU's GUID (checked by ``fmi2Instantiate``).
    description : str
        One line put into the file's head comment.
    u_start : float, default=0.0
        Start value of the input.

    Returns
    -------
    str
    """
    n = r.n_states
    safe = description.replace("*/", "* /")
    lines = [
        f"/* {safe}",
        " * FMI 2.0 co-simulation unit generated by kautztwin.export (exact zero-order-hold",
        " * recursion at a fixed step; see docs/export.md). */",
        _HEADER,
        "/* ---- the model ---- */",
        f'#define GUID "{guid}"',
        f"#define NX {n}",
        f"#define DELAY_STEPS {r.delay_steps}",
        f"#define NHIST {r.delay_steps + 1}",
        f"#define FRACTIONAL {1 if r.fractional else 0}",
        f"#define STEP {_num(r.h)}",
        f"#define U_START {_num(u_start)}",
        "#define U_OFFSET_START 0.0",
        "#define Y_OFFSET_START 0.0",
        f"#define VR_U {VR_U}",
        f"#define VR_Y {VR_Y}",
        f"#define VR_U_OFFSET {VR_U_OFFSET}",
        f"#define VR_Y_OFFSET {VR_Y_OFFSET}",
        _array("PHI", r.Phi),
        _array("GAMMA_A", r.Gamma_a),
        _array("GAMMA_B", r.Gamma_b),
        _array("C", r.C),
        f"static const double D = {_num(r.D)};",
        _BODY,
    ]
    return "\n".join(lines)


def new_guid() -> str:
    """A fresh GUID in braces, as FMI tools write them."""
    return "{" + str(uuid.uuid4()) + "}"


def model_description(
    r: DiscreteRealisation,
    *,
    model_identifier: str,
    model_name: str,
    guid: str,
    description: str,
    version: str,
    stop_time: float,
    u_start: float = 0.0,
) -> str:
    """The ``modelDescription.xml`` of the FMU (FMI 2.0, co-simulation).

    Parameters
    ----------
    r : DiscreteRealisation
        Its direct feedthrough decides the output's dependencies.
    model_identifier : str
        Name of the shared library and the C source (a C identifier).
    model_name, guid, description : str
    version : str
        The kautztwin version (``generationTool``).
    stop_time : float
        ``DefaultExperiment`` stop time.
    u_start : float, default=0.0
        Start value of the input.

    Returns
    -------
    str
    """
    now = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    # the output depends on the input at the same instant only through an undelayed D; at
    # initialisation it depends on all knowns (the offsets too), the default of no attribute
    feedthrough = r.D != 0.0 and r.delay_steps == 0 and not r.fractional
    deps = ' dependencies="1" dependenciesKind="constant"' if feedthrough else ' dependencies=""'
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription
  fmiVersion="2.0"
  modelName={quoteattr(model_name)}
  guid="{guid}"
  description={quoteattr(description)}
  generationTool="kautztwin {version}"
  generationDateAndTime="{now}"
  variableNamingConvention="flat"
  numberOfEventIndicators="0">
  <CoSimulation
    modelIdentifier="{model_identifier}"
    canHandleVariableCommunicationStepSize="false"
    canInterpolateInputs="false"
    canBeInstantiatedOnlyOncePerProcess="false"
    canNotUseMemoryManagementFunctions="true"
    canGetAndSetFMUstate="false"
    canSerializeFMUstate="false"
    providesDirectionalDerivative="false">
    <SourceFiles>
      <File name="{model_identifier}.c"/>
    </SourceFiles>
  </CoSimulation>
  <DefaultExperiment startTime="0" stopTime="{_num(stop_time)}" stepSize="{_num(r.h)}"/>
  <ModelVariables>
    <ScalarVariable name="u" valueReference="{VR_U}" causality="input" variability="continuous"
      description="input, held over each step">
      <Real start="{_num(u_start)}"/>
    </ScalarVariable>
    <ScalarVariable name="y" valueReference="{VR_Y}" causality="output" variability="continuous"
      initial="calculated" description="output">
      <Real/>
    </ScalarVariable>
    <ScalarVariable name="u_offset" valueReference="{VR_U_OFFSET}" causality="parameter"
      variability="fixed" initial="exact" description="level the model's input is measured from">
      <Real start="0"/>
    </ScalarVariable>
    <ScalarVariable name="y_offset" valueReference="{VR_Y_OFFSET}" causality="parameter"
      variability="fixed" initial="exact" description="output level added to the model's output">
      <Real start="0"/>
    </ScalarVariable>
  </ModelVariables>
  <ModelStructure>
    <Outputs>
      <Unknown index="2"{deps}/>
    </Outputs>
    <InitialUnknowns>
      <Unknown index="2"/>
    </InitialUnknowns>
  </ModelStructure>
</fmiModelDescription>
"""
