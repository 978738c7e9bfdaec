{{/* The release's base name, at most 63 characters. */}}
{{- define "rayd.fullname" -}}
{{- if contains .Chart.Name .Release.Name -}}
{{- .Release.Name | trunc 63 | trimSuffix "-" -}}
{{- else -}}
{{- printf "%s-%s" .Release.Name .Chart.Name | trunc 63 | trimSuffix "-" -}}
{{- end -}}
{{- end -}}

{{/* The headless Service, which gives each pod the stable name <pod>.<headless>. */}}
{{- define "rayd.headless" -}}
{{- printf "%s-headless" (include "rayd.fullname" .) | trunc 63 | trimSuffix "-" -}}
{{- end -}}

{{- define "rayd.labels" -}}
app.kubernetes.io/name: {{ .Chart.Name }}
app.kubernetes.io/instance: {{ .Release.Name }}
app.kubernetes.io/version: {{ .Chart.AppVersion | quote }}
app.kubernetes.io/managed-by: {{ .Release.Service }}
helm.sh/chart: {{ printf "%s-%s" .Chart.Name .Chart.Version }}
{{- end -}}

{{- define "rayd.selector" -}}
app.kubernetes.io/name: {{ .Chart.Name }}
app.kubernetes.io/instance: {{ .Release.Name }}
app.kubernetes.io/component: rayd
{{- end -}}

{{/* The Secret holding rayd.toml. */}}
{{- define "rayd.secret" -}}
{{- default (include "rayd.fullname" .) .Values.existingSecret -}}
{{- end -}}
